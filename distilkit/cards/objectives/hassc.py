"""Cards of HASSC's objectives (Wang et al., CVPR 2024): the self-distillation KD and the hard voxel mining
(:mod:`distilkit.objectives.hassc`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective


class HASSCKDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    dynamic_weight: bool = Field(True, description="times exp(mIoU of the teacher's argmax), the release's weight; "
                                                   "false: the KL term alone")
    classes: Literal["non_empty", "all"] = Field(
        "non_empty", description="the classes the dynamic weight's mIoU averages: 1..K-1, empty left out (the "
                                 "release's iou[1:]), or all K")
    per: Literal["sample", "batch"] = Field(
        "sample", description="the dynamic weight per sample, each sample's KL times exp(its own mIoU) (the release: "
                              "one sample per GPU), or one weight from the batch's voxels pooled")


class HASSCKDCard(ObjectiveCard):
    """HASSC's KD (card of :class:`distilkit.objectives.hassc.HASSCKD`), weight 48 as the release."""

    Params = HASSCKDParams
    MATCH = {"teacher": Match("equal", "same")}
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 48.0
    VERSION = 3  # 2: the dynamic weight per sample over classes 1..K-1 (was: the batch pooled, all K classes); 3: only
    # the valid voxels computed, each sample's sum pairwise (was: every voxel, masked; equal up to rounding)

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        return {"teacher": "valid"}  # the KL and the teacher's mIoU both count the valid voxels only

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher"})  # KL of softmax(t/T) and the argmax of the mIoU (argmax t = argmax softmax t)


class HardVoxelParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    points: int = Field(4096, ge=1, description="N: positions sampled per sample (the release's 4096)")
    oversample: int = Field(3, ge=1, description="t: uniform draws t·N among which the hardest are kept")
    omega: float = Field(0.75, ge=0, le=1, description="ω: the share of the N positions that are the hardest")
    alpha: float = Field(0.2, description="α of the local hardness α + β·LGA")
    beta: float = Field(1.0, description="β of the local hardness α + β·LGA")
    delta: float = Field(0.1, ge=0, description="δ: weight of the student's CE at the teacher's hard positions "
                                                "(0: the student branch only)")
    rank: Literal["probabilities", "logits"] = Field(
        "probabilities", description="hardness 1/(p1 − p2) of the two largest class probabilities (the paper) or of "
                                     "the two largest logits, sorted per voxel before interpolation (the release)")
    class_weights: Literal["log_frequency", "release"] = Field(
        "log_frequency", description="the normaliser's class weights: 10 / ln(f_c + 0.001) from the training split, "
                                     "or the release's SemanticKITTI table (20 classes)")
    reduce: Literal["per_sample", "pooled"] = Field(
        "per_sample", description="each branch's normalised sum per sample, then the mean over the samples (the "
                                  "release: one sample per GPU, DDP averaging), or the sums over the batch pooled "
                                  "(distilkit before v2)")


class HASSCHardVoxelsCard(ObjectiveCard):
    """HASSC's hard voxel mining (card of :class:`distilkit.objectives.hassc.HASSCHardVoxels`)."""

    Params = HardVoxelParams
    MATCH = {"teacher": Match("any", "resampled")}  # hard positions found in its scores at any size and width
    CONSUMES = {"student": "voxel_logits", "features": "volume_features", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 1.0
    VERSION = 2  # 2: per-sample ratios by default (was: the batch's sums pooled)

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # the teacher's hard positions are drawn anywhere in the volume (delta 0: the teacher is never read)
        return {"teacher": "occupied" if getattr(params, "delta") == 0 else "all"}

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        # hardness from softmax(interpolated t) or from interpolated t_(1) - t_(2) = log p_(1) - log p_(2): a
        # per-voxel shift of the scores cancels in both
        return frozenset({"teacher"})


declare_objective("hassc_kd", "distilkit.objectives.hassc:HASSCKD", HASSCKDCard,
                  description="HASSC's KD: per-voxel KL over valid voxels × exp(teacher mIoU), per sample",
                  paper="HASSC (Wang et al., CVPR 2024), utils/ssc_loss.py",
                  equation="mean_b exp(mIoU_T,b) · mean_{v valid in b} T² KL(softmax(t_v/T) ‖ softmax(s_v/T)); "
                           "mIoU over classes 1..K-1",
                  shapes="(B, K, X, Y, Z) logits, student and teacher")
declare_objective("hassc_hvm", "distilkit.objectives.hassc:HASSCHardVoxels", HASSCHardVoxelsCard,
                  description="HASSC's hard voxel mining: a 1×1 head at the hardest positions (CE × (α + β·LGA)) + δ × "
                              "the student's CE at the teacher's hard positions",
                  paper="HASSC (Wang et al., CVPR 2024), utils/hvm_header.py",
                  equation="mean_b [Σ_i CE(h([z_i, f_i]), y_i)(α + β·LGA_i) / Σ_i w_{y_i} + δ Σ_j CE(z_j, y_j)"
                           "(α + β·LGA_j) / Σ_j w_{y_j}]; i: the student's hard positions in b, j: the teacher's",
                  shapes="(B, K, X, Y, Z) logits, (B, C, X', Y', Z') voxel features", function="hard_voxel_ce")

__all__ = ["HASSCHardVoxelsCard", "HASSCKDCard", "HASSCKDParams", "HardVoxelParams"]
