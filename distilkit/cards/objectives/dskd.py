"""Card of DSKD, SCPNet eq. 1-2 on sparse voxel features (:mod:`distilkit.objectives.dskd`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective


class DSKDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    per_sample: bool = Field(True, description="relations within each scene, averaged over the batch "
                                               "(False: one relation matrix over all voxels of the batch)")


class DSKDCard(ObjectiveCard):
    """Dense-to-Sparse KD (card of :class:`distilkit.objectives.dskd.DSKD`), default weight beta = 3000."""

    Params = DSKDParams
    MATCH = {"teacher": Match("any", "aligned")}
    CONSUMES = {"student": "sparse_features", "teacher": "sparse_features"}
    DEFAULT_WEIGHT = 3000.0


declare_objective("dskd", "distilkit.objectives.dskd:DSKD", DSKDCard,
                  description="dense-to-sparse relational KD: squared gap of voxel cosine-similarity matrices",
                  paper="SCPNet (Xia et al., CVPR 2023), eq. 1-2",
                  equation="1/N² Σ_ij (cos_S(i,j) − cos_T(i,j))², exact via ‖AᵀA‖² + ‖BᵀB‖² − 2‖AᵀB‖²",
                  shapes="sparse voxel features; teacher rows at the student's voxels (across grids: a coarser "
                         "teacher read at the parent voxel, a finer one mean-pooled into the student's voxels)")

__all__ = ["DSKDCard", "DSKDParams"]
