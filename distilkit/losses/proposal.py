"""The losses of VoxFormer's stage 1 (query proposals, Li et al. CVPR 2023; seed_code.md §5): a depth regression on
the camera image and a class-weighted binary occupancy CE at the proposals' coarser resolution."""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.data.classes import IGNORE_INDEX
from distilkit.geometry.voxel import pool_occupancy
from distilkit.losses.ce import deterministic_form_needed, weighted_cross_entropy


def linear_resize_matrix(n_in: int, n_out: int, dtype: torch.dtype = torch.float64,
                         device: torch.device | str | None = None) -> Tensor:
    """(n_out, n_in): linear interpolation along one axis as ``F.interpolate(mode="bilinear", align_corners=False)``
    does it (source index (i + ½)·n_in/n_out − ½, clamped at 0; no antialiasing), as a matrix."""
    src = ((torch.arange(n_out, dtype=torch.float64) + 0.5) * (n_in / n_out) - 0.5).clamp_min(0.0)
    low = src.floor().long().clamp_max(n_in - 1)
    high = (low + 1).clamp_max(n_in - 1)
    frac = src - low
    rows = torch.arange(n_out)
    m = torch.zeros(n_out, n_in, dtype=torch.float64)
    m.index_put_((rows, low), 1.0 - frac, accumulate=True)
    m.index_put_((rows, high), frac, accumulate=True)
    return m.to(dtype=dtype, device=device)


def resize_bilinear(x: Tensor, size: tuple[int, int], deterministic: bool | None = None) -> Tensor:
    """(B, H, W) from (B, h, w): ``F.interpolate(x[:, None], size, mode="bilinear", align_corners=False)[:, 0]``.

    ``deterministic`` (default: off the CPU under deterministic algorithms,
    ``deterministic_form_needed``): as two products with interpolation matrices,
    A_H x A_Wᵀ (H × h and W × w), instead of PyTorch's kernel, whose CUDA backward PyTorch flags
    (``upsample_bilinear2d_backward_out_cuda does not have a deterministic implementation``). The same up to the
    rounding of the weights (float64: 1e-15); the products in float32 at least, outside autocast, the result in
    ``x``'s dtype."""
    if deterministic if deterministic is not None else deterministic_form_needed(x):
        work = torch.promote_types(x.dtype, torch.float32)
        with torch.autocast(x.device.type, enabled=False) if x.is_cuda else contextlib.nullcontext():
            rows = linear_resize_matrix(x.shape[1], size[0], work, x.device)
            cols = linear_resize_matrix(x.shape[2], size[1], work, x.device)
            return (rows @ x.to(work) @ cols.t()).to(x.dtype)
    return F.interpolate(x[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]


def depth_l1(pred: Tensor, target: Tensor, sky_depth: float | None = None) -> Tensor:
    """Mean absolute depth error (metres) over the pixels with a true depth (``target > 0``), and those without
    (sky) as ``sky_depth`` when given; ``pred`` (B, h, w) is resized bilinearly to the target's (B, H, W) first
    (``resize_bilinear``: deterministically on CUDA). 0 (with a gradient) where no pixel counts."""
    if pred.dim() != 3 or target.dim() != 3 or pred.shape[0] != target.shape[0]:
        raise ValueError(f"depth_l1: expects (B, h, w) predictions and (B, H, W) depths, got {tuple(pred.shape)} and "
                         f"{tuple(target.shape)}")
    if pred.shape != target.shape:
        pred = resize_bilinear(pred, (target.shape[1], target.shape[2]))
    if sky_depth is not None:
        target = target.masked_fill(target <= 0, sky_depth)
    valid = target > 0
    return (pred - target).abs().mul(valid).sum() / valid.sum().clamp_min(1)


def occupancy_ce(logits: Tensor, target: Tensor, alpha: float = 0.54, ignore_index: int = IGNORE_INDEX) -> Tensor:
    """VoxFormer's ``BCE_ssc_loss``: two-class CE with class weights (1 - alpha, alpha), normalised by the weights
    (``reduction='mean'``), on empty / occupied scores (B, 2, X', Y', Z') against the occupancy of the label grid
    (B, X, Y, Z) pooled to the scores' resolution (``distilkit.geometry.voxel.pool_occupancy``). Reduced
    deterministically on CUDA (:func:`~distilkit.losses.weighted_cross_entropy`: PyTorch flags the fused 'mean',
    ``nll_loss2d_forward_out_cuda_template``)."""
    if logits.dim() != 5 or logits.shape[1] != 2 or target.dim() != 4:
        raise ValueError(f"occupancy_ce: expects (B, 2, X, Y, Z) scores and (B, X, Y, Z) labels, got "
                         f"{tuple(logits.shape)} and {tuple(target.shape)}")
    factor = target.shape[1] // logits.shape[2]
    occupancy = pool_occupancy(target.long(), factor, ignore_index)
    if occupancy.shape[1:] != logits.shape[2:]:
        raise ValueError(f"occupancy_ce: scores on {tuple(logits.shape[2:])} do not divide the label grid "
                         f"{tuple(target.shape[1:])}")
    weight = torch.tensor([1.0 - alpha, alpha], dtype=logits.dtype, device=logits.device)
    if not bool((occupancy != ignore_index).any()):
        return logits.sum() * 0.0
    return weighted_cross_entropy(logits, occupancy, weight, ignore_index)


__all__ = ["depth_l1", "linear_resize_matrix", "occupancy_ce", "resize_bilinear"]
