"""Cards of L2COcc's distillation terms (Wang et al., IROS 2025): prediction alignment, numeric and relational
feature similarity (:mod:`distilkit.objectives.l2cocc`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective
from distilkit.cards.objectives.common import NoParams


class PADParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    include_empty: bool = Field(False, description="also the empty voxels (label 0): the release's distill_kl_empty")


class PADCard(ObjectiveCard):
    """L2COcc's prediction alignment (card of :class:`distilkit.objectives.l2cocc.PAD`), weight 70."""

    Params = PADParams
    MATCH = {"teacher": Match("equal", "same")}
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 70.0
    VERSION = 2  # 2: only the kept voxels computed, each sample's sum pairwise (was: every voxel, masked; equal up
    # to rounding)

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # the per-sample KL mean keeps the valid non-empty voxels (include_empty: the valid ones)
        return {"teacher": "valid" if getattr(params, "include_empty") else "occupied"}

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher"})  # KL(softmax(t) || softmax(s)) only


MAX_MAPS = 4  # map pairs one FSD term reads: student/teacher, student_2/teacher_2, ...
_EXTRA = [(f"student_{i}", f"teacher_{i}") for i in range(2, MAX_MAPS + 1)]


class FSDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    reduce: Literal["per_sample", "pooled"] = Field(
        "per_sample", description="each sample's mean over its positions, then the mean over the samples (the "
                                  "release: one sample per GPU, DDP averaging), or the mean over the batch's "
                                  "positions pooled (the release's code at B > 1 on one GPU; distilkit before v2)")


class FSDCard(ObjectiveCard):
    """L2COcc's numeric feature similarity (card of :class:`distilkit.objectives.l2cocc.FSD`): up to
    ``MAX_MAPS`` map pairs, weight 4."""

    Params = FSDParams
    MATCH = {role: Match("equal", "same", on_labels=True)
             for role in ("teacher", "teacher_2", "teacher_3", "teacher_4")}
    CONSUMES = {"student": "feature_map", "teacher": "feature_map",
                **{role: "feature_map" for pair in _EXTRA for role in pair}}
    TEACHER_ROLES = frozenset({"teacher", *(t for _, t in _EXTRA)})
    OPTIONAL = frozenset(role for pair in _EXTRA for role in pair)
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 4.0
    VERSION = 3  # 2: per-sample reduction by default, several map pairs averaged (was: pooled over the batch); 3: only
    # the masked positions computed, each sample's sum pairwise (was: every position, masked; equal up to rounding)

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # 1 - cos only where the label block is occupied: on the labels' grid, the occupied voxels
        return {role: "occupied" for role in sorted(cls.TEACHER_ROLES)}


class RelationCard(ObjectiveCard):
    """L2COcc's relational feature similarity (card of :class:`distilkit.objectives.l2cocc.Relation`), weight 5."""

    Params = NoParams
    MATCH = {"teacher": Match("any", "same")}  # P x P affinities: one number of positions
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 5.0


declare_objective("l2cocc_pad", "distilkit.objectives.l2cocc:PAD", PADCard,
                  description="L2COcc's prediction alignment: per-sample KLDivLoss mean over valid non-empty voxels",
                  paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                  equation="mean_b 1/(n_b K) Σ_{v valid, non-empty} Σ_k p_T (log p_T − log p_S)",
                  shapes="(B, K, X, Y, Z) logits, student and teacher")
declare_objective("l2cocc_fsd", "distilkit.objectives.l2cocc:FSD", FSDCard,
                  description="L2COcc's numeric feature similarity: 1 − cos over occupied positions, per sample, "
                              "averaged over the term's maps",
                  paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                  equation="mean_m mean_b mean_{p occupied in b} (1 − cos(f_S,p, f_T,p)); m: the term's map pairs",
                  shapes="(B, C, X, Y[, Z]) maps, each pair of one shape; labels pooled to each map")
declare_objective("l2cocc_relation", "distilkit.objectives.l2cocc:Relation", RelationCard,
                  description="L2COcc's relational similarity: L1 between P×P cosine matrices, in tiles of the upper "
                              "triangle",
                  paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                  equation="mean_{b,i,j} |cos_S(i,j) − cos_T(i,j)|",
                  shapes="(B, C_s / C_t, X, Y[, Z]) maps of one spatial size")

__all__ = ["MAX_MAPS", "FSDCard", "FSDParams", "NoParams", "PADCard", "PADParams", "RelationCard"]
