"""Cards of the logit objectives: vanilla KD and DIST on voxel logits (:mod:`distilkit.objectives.logit`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective
from distilkit.cards.objectives.common import MaskName


class KDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    voxels: MaskName = Field("valid", description="voxels distilled: all, valid (observed) or occupied")


class KDCard(ObjectiveCard):
    """Vanilla KD per voxel (card of :class:`distilkit.objectives.logit.KD`)."""

    Params = KDParams
    MATCH = {"teacher": Match("equal", "same")}
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}  # the labels that choose the voxels
    DEFAULT_WEIGHT = 1.0

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        return {"teacher": getattr(params, "voxels")}  # the KL of the other voxels is dropped before the mean

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher"})  # KL(softmax(t/T) || softmax(s/T)): the teacher only through its softmax


class DISTParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    beta: float = Field(1.0, ge=0, description="inter-class (per voxel) weight")
    gamma: float = Field(1.0, ge=0, description="intra-class (per class across voxels) weight")
    temperature: float = Field(1.0, gt=0)
    voxels: MaskName = "valid"


class DISTCard(ObjectiveCard):
    """DIST with voxels as the rows (card of :class:`distilkit.objectives.logit.DIST`)."""

    Params = DISTParams
    MATCH = {"teacher": Match("equal", "same")}
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}  # the labels that choose the voxels
    DEFAULT_WEIGHT = 1.0

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        return {"teacher": getattr(params, "voxels")}  # the rows (voxels) outside the mask are dropped first

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher"})  # Pearson correlations of softmax(t/T) only


declare_objective("kd", "distilkit.objectives.logit:KD", KDCard,
                  description="vanilla KD: per-voxel KL of softened class distributions (T² scaled)",
                  paper="Hinton et al. 2015; SCPNet Table 4, Scribble2Scene Table 5",
                  equation="T² · mean_v KL(softmax(t_v/T) ‖ softmax(s_v/T))",
                  shapes="(B, K, X, Y, Z) logits, student and teacher")
declare_objective("dist", "distilkit.objectives.logit:DIST", DISTCard,
                  description="DIST: Pearson correlation of class distributions, inter- and intra-class",
                  paper="Huang et al., NeurIPS 2022; Scribble2Scene Table 5",
                  equation="T²(β(1 − mean_v ρ(p_s,v, p_t,v)) + γ(1 − mean_k ρ(p_s,:k, p_t,:k)))",
                  shapes="(B, K, X, Y, Z) logits; rows = selected voxels")

__all__ = ["DISTCard", "DISTParams", "KDCard", "KDParams"]
