"""Logit objectives: vanilla KD and DIST on voxel logits."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from distilkit.cards.objectives.logit import DISTCard, DISTParams, KDCard, KDParams
from distilkit.data.batch import Batch
from distilkit.losses.logit import dist, kd
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.common import voxel_mask


class KD(KDCard, MultiTapObjective):
    """Vanilla KD (Hinton et al. 2015) per voxel: T^2 mean KL(p_t || p_s) over the chosen voxels.

    Per-voxel mean, so the weight does not depend on the grid size (SCPNet Table 4 baseline).
    """

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        mask = voxel_mask(taps["target"], self.params.voxels, self.ignore_index)
        return kd(taps["student"], taps["teacher"], self.params.temperature, mask)


class DIST(DISTCard, MultiTapObjective):
    """DIST (Huang et al., NeurIPS 2022) with voxels as the rows (Scribble2Scene Table 5 baseline)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        student, teacher = taps["student"], taps["teacher"]
        k = student.shape[1]
        rows_s = student.movedim(1, -1).reshape(-1, k)
        rows_t = teacher.movedim(1, -1).reshape(-1, k)
        mask = voxel_mask(taps["target"], self.params.voxels, self.ignore_index)
        if mask is not None:
            rows_s, rows_t = rows_s[mask.reshape(-1)], rows_t[mask.reshape(-1)]
        p = self.params
        return dist(rows_s, rows_t, p.beta, p.gamma, p.temperature)


__all__ = ["DIST", "DISTParams", "KD", "KDParams"]
