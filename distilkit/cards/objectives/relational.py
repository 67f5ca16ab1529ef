"""Cards of the relational objectives on sparse voxel features: PKT and PVKD
(:mod:`distilkit.objectives.relational`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective
from distilkit.cards.objectives.common import MaskName


class PKTParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sample_size: int = Field(4096, ge=2, description="voxels sampled per scene from the student's active set")
    shared_only: bool = Field(True, description="sample only voxels the teacher also has")
    per_row: bool = Field(True, description="multiply by the sample size: the mean KL per row, so the weight "
                                            "does not depend on sample_size (RepDistiller's value scales as 1/N)")


class PKTCard(ObjectiveCard):
    """PKT over sampled voxels (card of :class:`distilkit.objectives.relational.PKT`)."""

    Params = PKTParams
    MATCH = {"teacher": Match("any", "aligned")}
    CONSUMES = {"student": "sparse_features", "teacher": "sparse_features"}
    DEFAULT_WEIGHT = 500.0


class PVKDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    output_weight: float = Field(1.0, ge=0, description="voxel-wise output KD term")
    affinity_weight: float = Field(100.0, ge=0, description="inter-voxel affinity term (not released by the authors)")
    radial_bins: int = Field(8, ge=1)
    angular_bins: int = Field(8, ge=1)
    height_bins: int = Field(2, ge=1)
    num_supervoxels: int | None = Field(None, ge=1, description="supervoxels sampled per step (None: all)")
    voxels: MaskName = "valid"


class PVKDCard(ObjectiveCard):
    """PVKD as SCPNet Table 4 uses it (card of :class:`distilkit.objectives.relational.PVKD`)."""

    Params = PVKDParams
    MATCH = {"teacher": Match("any", "aligned"), "teacher_logits": Match("equal", "same")}
    CONSUMES = {"student": "sparse_features", "teacher": "sparse_features",
                "student_logits": "voxel_logits", "teacher_logits": "voxel_logits"}
    TEACHER_ROLES = frozenset({"teacher", "teacher_logits"})
    BATCH = {"target": "voxel_target"}  # the labels that choose the voxels of the output term
    DEFAULT_WEIGHT = 1.0

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # the output KD's masked mean reads the logits at the mask; the features are sparse (not on a dense grid)
        return {"teacher": "all", "teacher_logits": getattr(params, "voxels")}

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher_logits"})  # the output term is KD (softmax(t/T)); the features are not scores


declare_objective("pkt", "distilkit.objectives.relational:PKT", PKTCard,
                  description="PKT: KL between cosine-kernel probability distributions over sampled voxels",
                  paper="Passalis & Tefas, ECCV 2018; SCPNet Table 4",
                  equation="mean_ij p_t,ij log((p_t,ij + ε)/(p_s,ij + ε)), p_ij = k_ij / Σ_j k_ij, k = (cos + 1)/2",
                  shapes="sparse voxel features; M ≤ sample_size rows per scene (across grids: as dskd)")
declare_objective("pvkd", "distilkit.objectives.relational:PVKD", PVKDCard,
                  description="PVKD: voxel-wise output KD + inter-voxel affinity inside cylindrical supervoxels",
                  paper="Hou et al., CVPR 2022; SCPNet Table 4",
                  equation="w_o · KD(s, t) + w_a · mean_sv ‖Â_sv Â_svᵀ − B̂_sv B̂_svᵀ‖² / n_sv²",
                  shapes="sparse voxel features (across grids: as dskd) and (B, K, X, Y, Z) logits on one grid")

__all__ = ["PKTCard", "PKTParams", "PVKDCard", "PVKDParams"]
