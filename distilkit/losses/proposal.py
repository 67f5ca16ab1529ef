"""The losses of VoxFormer's stage 1 (query proposals, Li et al. CVPR 2023; seed_code.md §5): a depth regression on
the camera image and a class-weighted binary occupancy CE at the proposals' coarser resolution."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.data.classes import IGNORE_INDEX
from distilkit.geometry.voxel import pool_occupancy


def depth_l1(pred: Tensor, target: Tensor, sky_depth: float | None = None) -> Tensor:
    """Mean absolute depth error (metres) over the pixels with a true depth (``target > 0``), and those without
    (sky) as ``sky_depth`` when given; ``pred`` (B, h, w) is resized bilinearly to the target's (B, H, W) first.
    0 (with a gradient) where no pixel counts."""
    if pred.dim() != 3 or target.dim() != 3 or pred.shape[0] != target.shape[0]:
        raise ValueError(f"depth_l1: expects (B, h, w) predictions and (B, H, W) depths, got {tuple(pred.shape)} and "
                         f"{tuple(target.shape)}")
    if pred.shape != target.shape:
        pred = F.interpolate(pred[:, None], size=target.shape[1:], mode="bilinear", align_corners=False)[:, 0]
    if sky_depth is not None:
        target = target.masked_fill(target <= 0, sky_depth)
    valid = target > 0
    return (pred - target).abs().mul(valid).sum() / valid.sum().clamp_min(1)


def occupancy_ce(logits: Tensor, target: Tensor, alpha: float = 0.54, ignore_index: int = IGNORE_INDEX) -> Tensor:
    """VoxFormer's ``BCE_ssc_loss``: two-class CE with class weights (1 - alpha, alpha), normalised by the weights
    (``reduction='mean'``), on empty / occupied scores (B, 2, X', Y', Z') against the occupancy of the label grid
    (B, X, Y, Z) pooled to the scores' resolution (:func:`~distilkit.geometry.voxel.pool_occupancy`)."""
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
    return F.cross_entropy(logits, occupancy, weight=weight, ignore_index=ignore_index)


__all__ = ["depth_l1", "occupancy_ce"]
