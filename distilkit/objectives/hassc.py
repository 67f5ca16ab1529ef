"""HASSC's objectives (Wang et al., CVPR 2024; release songw-zju/HASSC): the self-distillation KD
(``utils/ssc_loss.py``: per-voxel KL over the valid voxels, times exp(the teacher's mIoU on the sample)) and the hard
voxel mining with its small head (``utils/hvm_header.py``). HASSC's teacher is the student's own moving average
(``teacher: {ema: true}``); its geometry-weighted CE is the task loss ``hassc_ce``."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.objectives.hassc import HardVoxelParams, HASSCHardVoxelsCard, HASSCKDCard, HASSCKDParams
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.errors import DistilkitError
from distilkit.losses.hassc import hassc_kd, teacher_batch_miou
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.common import release_labels


class HASSCKD(HASSCKDCard, MultiTapObjective):
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
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        teacher = taps["teacher"].detach()
        p = self.params
        miou = teacher_batch_miou(teacher, labels, classes=p.classes, per=p.per) if p.dynamic_weight else None
        return hassc_kd(taps["student"], teacher, labels, p.temperature, miou)


class HASSCHardVoxels(HASSCHardVoxelsCard, MultiTapObjective):
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


__all__ = ["HASSCHardVoxels", "HASSCKD", "HASSCKDParams", "HardVoxelParams"]
