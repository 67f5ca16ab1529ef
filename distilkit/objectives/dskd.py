"""DSKD objective: SCPNet eq. 1-2 on index-aligned sparse voxel features."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.cards.objectives.dskd import DSKDCard, DSKDParams
from distilkit.data.batch import Batch
from distilkit.objectives.common import aligned_pairs
from distilkit.losses.dskd import dskd
from distilkit.objectives.base import Objective
from distilkit.structures import SparseVoxels


class DSKD(DSKDCard, Objective):
    """Dense-to-Sparse KD (Xia et al., SCPNet, CVPR 2023, eq. 1-2), default weight beta = 3000.

    Alignment: the student's non-empty voxels are the reference set; teacher features are
    gathered at the student's coordinates and are zero where the teacher has no voxel (so their
    relations count as 0). Across grids of the same volume that differ by integer factors, a
    coarser teacher is gathered at the student's scaled coordinates (its parent voxel) and a finer
    teacher is first mean-pooled over the active child voxels of each student voxel. The loss is
    computed exactly over all voxels (no sampling).
    """

    def forward(self, student: SparseVoxels, teacher: SparseVoxels, batch: Batch) -> Tensor:
        s_feats, t_feats, _ = aligned_pairs(student, teacher)
        if not self.params.per_sample:
            return dskd(s_feats, t_feats)
        b = student.coords[:, 0]
        losses = [dskd(s_feats[b == i], t_feats[b == i]) for i in torch.unique(b).tolist()]
        if not losses:
            return s_feats.sum() * 0.0
        return torch.stack(losses).mean()


__all__ = ["DSKD", "DSKDParams"]
