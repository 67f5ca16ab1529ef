"""The Chamfer distance as a training loss (LiDiff's refinement: ``pytorch3d.loss.chamfer_distance`` with its defaults,
seed_code.md §3.3): squared Euclidean distances to the nearest point of the other set, averaged over each set's
points, the two directions summed, then averaged over the batch's scenes."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.geometry.nearest import nearest
from distilkit.structures import PointCloud


def _one(pred: Tensor, target: Tensor) -> Tensor:
    if pred.shape[0] == 0 or target.shape[0] == 0:
        raise ValueError(f"chamfer: empty point set (prediction {pred.shape[0]}, target {target.shape[0]} points)")
    to_target = (pred - target[nearest(pred, target)]).pow(2).sum(dim=1).mean()
    to_pred = (target - pred[nearest(target, pred)]).pow(2).sum(dim=1).mean()
    return to_target + to_pred


def chamfer(pred: Tensor | PointCloud, target: Tensor | PointCloud) -> Tensor:
    """mean_p min_g ||p - g||^2 + mean_g min_p ||g - p||^2 for two (M, 3) sets, or its mean over the scenes of two
    padded batches (PointClouds with lengths). Nearest neighbours are found without gradient; the distances carry
    it to both sets."""
    if isinstance(pred, PointCloud) != isinstance(target, PointCloud):
        raise TypeError("give both point sets as (M, 3) tensors or both as PointClouds")
    if isinstance(pred, PointCloud):
        assert isinstance(target, PointCloud)
        if len(pred.lengths) != len(target.lengths):
            raise ValueError(f"chamfer: {len(pred.lengths)} predicted scenes but {len(target.lengths)} targets")
        return torch.stack([_one(pred.cloud(b), target.cloud(b)) for b in range(len(pred.lengths))]).mean()
    return _one(pred, target)


__all__ = ["chamfer"]
