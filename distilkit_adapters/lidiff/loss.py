"""LiDiff's training loss: the denoising MSE and a regulariser on the predicted noise's statistics."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from distilkit.data.batch import Batch
from distilkit.losses.task import TaskLoss
from distilkit.structures import PointCloud
from distilkit_adapters.lidiff.card import LiDiffLossCard, LiDiffLossParams


def _valid(cloud: PointCloud) -> Tensor:
    return torch.cat([cloud.cloud(b) for b in range(len(cloud.lengths))])


class LiDiffLoss(LiDiffLossCard, TaskLoss):
    """MSE(eps_hat, eps) + w (mean(eps_hat)^2 + (std(eps_hat) - 1)^2), statistics over every point of the batch
    (LiDiff's ``reg_weight`` = 5; seed_code.md §3.1); ScoreLiDAR eq. 5 is its first term."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        pred, eps = _valid(taps["student"]), _valid(taps["noise"])
        reg = pred.mean() ** 2 + (pred.std() - 1.0) ** 2
        return torch.nn.functional.mse_loss(pred, eps) + self.params.reg_weight * reg


__all__ = ["LiDiffLoss", "LiDiffLossParams"]
