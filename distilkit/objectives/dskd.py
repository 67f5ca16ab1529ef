"""DSKD objective: SCPNet eq. 1-2 on index-aligned sparse voxel features."""

from __future__ import annotations

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.data.batch import Batch
from distilkit.objectives.common import aligned_pairs
from distilkit.losses.dskd import dskd
from distilkit.objectives.base import Objective, register_objective
from distilkit.structures import SparseVoxels


class DSKDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    per_sample: bool = Field(True, description="relations within each scene, averaged over the batch "
                                               "(False: one relation matrix over all voxels of the batch)")


class DSKD(Objective):
    """Dense-to-Sparse KD (Xia et al., SCPNet, CVPR 2023, eq. 1-2), default weight beta = 3000.

    Alignment: the student's non-empty voxels are the reference set; teacher features are
    gathered at the student's coordinates and are zero where the teacher has no voxel (so their
    relations count as 0). Across grids of the same volume that differ by integer factors, a
    coarser teacher is gathered at the student's scaled coordinates (its parent voxel) and a finer
    teacher is first mean-pooled over the active child voxels of each student voxel. The loss is
    computed exactly over all voxels (no sampling).
    """

    Params = DSKDParams
    CONSUMES = {"student": "sparse_features", "teacher": "sparse_features"}
    DEFAULT_WEIGHT = 3000.0

    def forward(self, student: SparseVoxels, teacher: SparseVoxels, batch: Batch) -> Tensor:
        s_feats, t_feats, _ = aligned_pairs(student, teacher)
        if not self.params.per_sample:
            return dskd(s_feats, t_feats)
        b = student.coords[:, 0]
        losses = [dskd(s_feats[b == i], t_feats[b == i]) for i in torch.unique(b).tolist()]
        if not losses:
            return s_feats.sum() * 0.0
        return torch.stack(losses).mean()


register_objective("dskd", DSKD, description="dense-to-sparse relational KD: squared gap of voxel cosine-similarity matrices",
               paper="SCPNet (Xia et al., CVPR 2023), eq. 1-2",
               equation="1/N² Σ_ij (cos_S(i,j) − cos_T(i,j))², exact via ‖AᵀA‖² + ‖BᵀB‖² − 2‖AᵀB‖²",
               shapes="sparse voxel features; teacher rows at the student's voxels (across grids: a coarser "
                      "teacher read at the parent voxel, a finer one mean-pooled into the student's voxels)")
