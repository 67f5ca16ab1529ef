"""HASSC's objectives (Wang et al., CVPR 2024; release songw-zju/HASSC): the self-distillation KD
(``utils/ssc_loss.py``: per-voxel KL over the valid voxels, times exp(the teacher's mIoU on the sample)) and the hard
voxel mining with its small head (``utils/hvm_header.py``). HASSC's teacher is the student's own moving average
(``teacher: {ema: true}``); its geometry-weighted CE is the task loss ``hassc_ce``."""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.errors import DistilkitError
from distilkit.losses.hassc import hassc_kd, teacher_batch_miou
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.common import release_labels


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


class HASSCKD(MultiTapObjective):
    """HASSC's KD: T^2 KL(p_T || p_S) per valid voxel, the mean per sample, times exp(the teacher's mIoU over
    classes 1..K-1 on that sample), then the mean over the samples (the release, one sample per GPU, DDP averaging
    the gradients; ``per: batch``: one weight from the batch pooled); weight 48 as the release. Reduction: the mean
    of per-sample values, as the release at B > 1. HASSC's teacher is the student's own EMA; any teacher edge
    serves."""

    CHOICES = (Choice("the batch reduction", "the mean of per-sample values (each sample's mean over its valid "
                      "voxels)", "not stated", "one sample per GPU (samples_per_gpu=1), DDP averaging: the mean of "
                      "per-sample values; its distill_ssc_loss sums the per-sample means (the same at one sample)"),
               Choice("the dynamic weight's mIoU: classes", "classes 1..K-1 (empty left out), a class absent from "
                      "prediction and label IoU 0 (TP / (TP + FP + FN + 1e-5)), as the release",
                      "the teacher's mIoU", "dense_heads/hassc_voxformer_head.py: teacher_ssc_iou[1:].mean(), "
                      "ssc_metric_torch.py's IoU with + 1e-5 (an absent class: 0)", "`classes: all` (all K classes; "
                      "distilkit before v2)"),
               Choice("the dynamic weight's mIoU: over what", "each sample's own mIoU weighs its own KL",
                      "the teacher's mIoU", "one sample per GPU: exp(that sample's mIoU) on that GPU",
                      "`per: batch` (one mIoU from the batch's voxels pooled; distilkit before v2)"),
               Choice("the teacher's mode", "eval", "a mean teacher (the release calls teacher.eval())",
                      "train: mmcv's runner calls model.train() on the detector holding it "
                      "(detectors/hassc_voxformer.py)", "`teacher: {mode: train}` (or `ema: {mode: train}`)"))
    Params = HASSCKDParams
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 48.0
    VERSION = 2  # 2: the dynamic weight per sample over classes 1..K-1 (was: the batch pooled, all K classes)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        teacher = taps["teacher"].detach()
        p = self.params
        miou = teacher_batch_miou(teacher, labels, classes=p.classes, per=p.per) if p.dynamic_weight else None
        return hassc_kd(taps["student"], teacher, labels, p.temperature, miou)


register_objective("hassc_kd", HASSCKD, description="HASSC's KD: per-voxel KL over valid voxels × exp(teacher "
                   "mIoU), per sample", paper="HASSC (Wang et al., CVPR 2024), utils/ssc_loss.py",
                   equation="mean_b exp(mIoU_T,b) · mean_{v valid in b} T² KL(softmax(t_v/T) ‖ softmax(s_v/T)); "
                            "mIoU over classes 1..K-1",
                   shapes="(B, K, X, Y, Z) logits, student and teacher")


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


class HASSCHardVoxels(MultiTapObjective):
    """HASSC's hard voxel mining (§3.2–3.3; release ``utils/hvm_header.py`` and the head's ``step``).

    Student branch: N positions per sample (:func:`~distilkit.losses.hardness.sample_hard_voxels` on the student's
    prediction), a 1×1 head — this objective's own parameters, trained with the student and never part of the
    exported student — on [the prediction, the voxel features] read there (trilinear) predicts the class, with CE ×
    (α + β·LGA) normalised by the class weights of the sampled labels. Teacher branch (weight δ): the same CE on the
    student's prediction (nearest) at the positions the teacher's prediction finds hard. Random draws: the student
    branch's t·N then N − ω·N positions, then the teacher's, from the device's default generator (part of a
    checkpoint, so a resumed run draws the same). Reduction (``reduce``): each branch's ratio per sample, then the
    mean over the samples (the release's one sample per GPU); ``pooled``: the sums over the batch."""

    CHOICES = (
        Choice("hardness", "1/(p1 − p2) of the two largest probabilities of the interpolated prediction",
               "1/(p1 − p2) of the two largest probabilities", "of the two largest logits (sorted per voxel, then "
               "interpolated)", "`rank: logits`"),
        Choice("sampling with B > 1", "each sample its own hardest positions", "per sample",
               "the kept positions gathered from the flattened batch with per-sample indices (sample 0's for all)", ""),
        Choice("the teacher branch's normaliser", "the class weights of the sampled labels, as the student branch",
               "not stated", "the class weights indexed by the sampled LGA values", ""),
        Choice("the coarse prediction", "the student's (teacher's) voxel-logits tap, read at any resolution",
               "a coarse occupancy head's output", "a 3x3 conv + GN head on the half-resolution volume, upsampled x2 "
               "to the final logits", "`taps: {student: ..., teacher: ...}`"),
        Choice("LGA", "derived from the labels per batch (6 face neighbours with another label)",
               "local geometric anisotropy", "precomputed files (values 0-6), truncated to integers when sampled", ""),
        Choice("the batch reduction", "the mean over the samples of each sample's Σ CE (α + β·LGA) / Σ w_y",
               "not stated", "one sample per GPU (samples_per_gpu=1), DDP averaging: the mean of per-sample ratios",
               "`reduce: pooled` (Σ over the batch / Σ over the batch)"),
    )
    Params = HardVoxelParams
    CONSUMES = {"student": "voxel_logits", "features": "volume_features", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 1.0
    VERSION = 2  # 2: per-sample ratios by default (was: the batch's sums pooled)

    def __init__(self, params: HardVoxelParams) -> None:
        super().__init__(params)
        self.head: nn.Module = nn.Identity()
        self.register_buffer("class_weight", torch.ones(1))

    def prepare(self, train_set: Any) -> None:
        from distilkit.losses.ssc import class_weights

        try:
            self.class_weight = class_weights(self.params.class_weights, train_set, self.num_classes).to(
                self.class_weight)
        except ValueError as exc:
            raise DistilkitError(f"hassc_hvm: {exc}") from None

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        k, c = taps["student"].shape[1], taps["features"].shape[1]
        self.head = nn.Conv1d(k + c, k, 1)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.hardness import hard_voxel_ce, local_geometric_anisotropy, sample_hard_voxels, \
            voxel_sample

        p = self.params
        logits, feats, teacher = taps["student"], taps["features"], taps["teacher"].detach()
        if logits.dim() != 5 or feats.dim() != 5 or feats.shape[0] != logits.shape[0]:
            raise ValueError(f"hassc_hvm: the prediction {tuple(logits.shape)} and the voxel features "
                             f"{tuple(feats.shape)} must be (B, K, X, Y, Z) and (B, C, X', Y', Z')")
        labels = release_labels(taps["target"], self.ignore_index)
        volume = torch.stack([labels.float(), local_geometric_anisotropy(labels)], 1)  # read together, nearest
        weights = self.class_weight.to(logits.dtype)

        coords = sample_hard_voxels(logits.detach(), p.points, p.oversample, p.omega, p.rank)
        at = torch.cat([voxel_sample(logits, coords), voxel_sample(feats.to(logits.dtype), coords)], 1)
        truth = voxel_sample(volume, coords, "nearest")
        loss = hard_voxel_ce(self.head(at), truth[:, 0].long(), truth[:, 1], weights, p.alpha, p.beta,
                             reduce=p.reduce)
        if p.delta > 0:
            coords = sample_hard_voxels(teacher, p.points, p.oversample, p.omega, p.rank)
            truth = voxel_sample(volume, coords, "nearest")
            student_at = voxel_sample(logits, coords, "nearest")
            loss = loss + p.delta * hard_voxel_ce(student_at, truth[:, 0].long(), truth[:, 1], weights, p.alpha,
                                                  p.beta, reduce=p.reduce)
        return loss


register_objective("hassc_hvm", HASSCHardVoxels, description="HASSC's hard voxel mining: a 1×1 head at the hardest "
                   "positions (CE × (α + β·LGA)) + δ × the student's CE at the teacher's hard positions",
                   paper="HASSC (Wang et al., CVPR 2024), utils/hvm_header.py",
                   equation="mean_b [Σ_i CE(h([z_i, f_i]), y_i)(α + β·LGA_i) / Σ_i w_{y_i} + δ Σ_j CE(z_j, y_j)"
                            "(α + β·LGA_j) / Σ_j w_{y_j}]; i: the student's hard positions in b, j: the teacher's",
                   shapes="(B, K, X, Y, Z) logits, (B, C, X', Y', Z') voxel features", function="hard_voxel_ce")
