"""Bird's-eye view from voxels: the height collapse and the voxel-to-BEV distillation of Jiang et al. (arXiv
2304.11393, "Knowledge distillation from 3D to bird's-eye-view for LiDAR semantic segmentation"; release
fengjiang5/Knowledge-Distillation-from-Cylinder3D-to-PolarNet at b5f136e, code of ddf0e21).

* :func:`collapse_height` — a (B, C, X, Y, Z) volume or sparse voxels onto the (X, Y) plane, per channel the max
  (the release: ``torch_scatter.scatter_max`` over the active voxels of each column, ``kd/cross_attn_spconv121.py``
  L54-61; an empty column 0, a column's max may be negative) or the mean. Ties of the max share its gradient
  equally (``scatter_reduce``'s rule; ``scatter_max`` gives it to one of them).
* :func:`column_weights` — the release's label weight of a BEV cell (``train_SemanticKITTI.py`` get_weight L43-47,
  L176; ``kd/weight_mse.py`` L15): the sum over the column's voxels of the weight of each voxel's class. The
  release's class weight is 1 / (f_c + 0.001) / 50 with f_c the class's share of the training points, the empty
  (and unlabelled: one class there) voxels counted as class 0: an empty column weighs 32 x 0.615 = 19.7 at its 32
  heights, a column of rare classes up to 617. Not a height, and not normalised by the weights' sum.
* :func:`bev_from_voxels` — with ``weights`` the label-weighted distance (LWD, ``kd/weight_mse.py`` L11-17):
  sqrt(mean_{b,i,j} W_bij sum_c (T - S)^2) — summed over the channels, averaged over the B H W cells, square root
  (``root=False``: without it); without weights the plain MSE of the voxel-to-pillar terms (VPD, train L177-178:
  ``MSELoss`` mean over B C H W, no root). ``T`` is the teacher's collapsed map after the release's adapter
  (:mod:`distilkit.objectives.bev`), which trains with the student: the target is not detached.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.structures import SparseVoxels

Collapse = Literal["max", "mean"]
COLLAPSES = ("max", "mean")


def collapse_height(value: Any, how: Collapse = "max", batch: int | None = None) -> Tensor:
    """(B, C, X, Y): ``value`` — (B, C, X, Y, Z) features or :class:`~distilkit.taps.SparseVoxels` (coords batch, x, y, z) —
    reduced over Z per channel by ``how`` (sparse: over each column's active voxels; a column without one is 0).
    ``batch``: the batch size of sparse voxels (default: the largest batch index + 1)."""
    if how not in COLLAPSES:
        raise ValueError(f"collapse_height: how must be max or mean, got {how!r}")
    if isinstance(value, SparseVoxels):
        x, y = int(value.spatial_shape[0]), int(value.spatial_shape[1])
        coords, feats = value.coords.long(), value.feats
        b = batch if batch is not None else (int(coords[:, 0].max()) + 1 if len(coords) else 1)
        column = (coords[:, 0] * x + coords[:, 1]) * y + coords[:, 2]
        out = feats.new_zeros(b * x * y, feats.shape[1])
        out = out.scatter_reduce(0, column[:, None].expand_as(feats), feats, "amax" if how == "max" else "mean",
                                 include_self=False)
        return out.view(b, x, y, feats.shape[1]).permute(0, 3, 1, 2)
    if isinstance(value, Tensor) and value.dim() == 5:
        return value.amax(dim=4) if how == "max" else value.mean(dim=4)
    shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
    raise ValueError(f"collapse_height: expected (B, C, X, Y, Z) features or SparseVoxels, got {shape}")


def column_weights(labels: Tensor, class_weights: Tensor, shape: tuple[int, int] | None = None,
                   ignore_index: int = 255) -> Tensor:
    """(B, X, Y): the sum over each column of labels (B, X, Y, Z) of its voxels' class weights (K,); a voxel of
    ``ignore_index`` weighs as class 0 (the release has one class for empty and unlabelled). ``shape``: a coarser
    (H, W) plane, each cell the mean of its block of columns (the release uses the label grid's plane only)."""
    if labels.dim() != 4:
        raise ValueError(f"column_weights: labels must be (B, X, Y, Z), got {tuple(labels.shape)}")
    index = torch.where(labels == ignore_index, torch.zeros_like(labels), labels).long()
    if index.numel() and int(index.max()) >= len(class_weights):
        raise ValueError(f"column_weights: a label {int(index.max())} has no class weight ({len(class_weights)} "
                         "given)")
    weights = class_weights[index].sum(dim=3)
    if shape is None or tuple(shape) == tuple(weights.shape[1:]):
        return weights
    factors = [a // b if b and a % b == 0 else 0 for a, b in zip(weights.shape[1:], shape)]
    if not all(factors):
        raise ValueError(f"column_weights: the label plane {tuple(weights.shape[1:])} is not an integer multiple of "
                         f"the map {tuple(shape)}")
    return F.avg_pool2d(weights[:, None], kernel_size=factors)[:, 0]


def bev_from_voxels(student: Tensor, teacher: Tensor, weights: Tensor | None = None, root: bool = True) -> Tensor:
    """The voxel-to-BEV distance between a BEV student's map and the teacher's collapsed, adapted map, both
    (B, C, H, W): with ``weights`` (B, H, W), [sqrt of] the mean over the cells of W sum_c (T - S)^2 (LWD); without,
    the mean over every element of (T - S)^2 (VPD)."""
    if student.shape != teacher.shape or student.dim() != 4:
        raise ValueError(f"bev_from_voxels: maps {tuple(student.shape)} and {tuple(teacher.shape)} must be one "
                         "(B, C, H, W) shape")
    diff = (teacher.to(student.dtype) - student).pow(2)
    if weights is None:
        return diff.mean()
    if weights.shape != student.shape[:1] + student.shape[2:]:
        raise ValueError(f"bev_from_voxels: weights {tuple(weights.shape)} must be (B, H, W) of the maps "
                         f"{tuple(student.shape)}")
    value = (weights.to(student.dtype) * diff.sum(1)).mean()
    # the root's gradient is infinite at 0: below the smallest normal number the value is that number's root
    return value.clamp_min(torch.finfo(value.dtype).tiny).sqrt() if root else value


__all__ = ["COLLAPSES", "bev_from_voxels", "collapse_height", "column_weights"]
