"""The task losses (supervised terms of a stage): CE, Lovász-softmax, uncertainty weighting. Their declarations
and registrations are their cards' (:mod:`distilkit.cards.task_losses`); this module holds what computes."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.base import NoParams
from distilkit.cards.task_losses import (ChamferCard, ClassWeightedCard, DepthL1Card, GeoScalCard,
                                         GeometryWeightedCECard, OccupancyCECard, PartialCECard, SemScalCard,
                                         UncertaintyMultiTaskCard, VoxelCECard, VoxelLossCard, VoxelLovaszCard,
                                         WeightedCECard, _CEParams, _DepthParams, _GeometryCEParams, _LovaszParams,
                                         _OccupancyParams, _PartialParams, _UncParams, _WeightedCEParams,
                                         _WeightedParams)
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX, NUM_CLASSES
from distilkit.errors import DistilkitError
from distilkit.losses.chamfer import chamfer
from distilkit.losses.segmentation import cross_entropy, lovasz_softmax
from distilkit.term import Term


class TaskLoss(Term):
    """A supervised term (:class:`~distilkit.term.Term` with no teacher role): its targets are batch roles."""


class VoxelCE(VoxelCECard, TaskLoss):
    """Cross entropy on voxel logits against ``voxel_target`` (invalid voxels ignored)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return cross_entropy(taps["student"], taps["target"], self.params.ignore_index)


class VoxelLovasz(VoxelLovaszCard, TaskLoss):
    """Lovász-softmax on voxel logits (SCPNet eq. 4, alpha term)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return lovasz_softmax(taps["student"], taps["target"], self.params.ignore_index, self.params.classes)


def frequency_weights(counts: Tensor, power: float = 1.0 / 3.0) -> Tensor:
    """JS3C-Net's class weights (max_c f_c / f_c)^(1/3); a class that never occurs gets the largest weight."""
    counts = counts.double()
    present = counts > 0
    if not bool(present.any()):
        return torch.ones_like(counts, dtype=torch.float32)
    f = counts / counts.sum()
    w = torch.where(present, (f.max() / f.clamp_min(1e-30)) ** power, torch.zeros_like(f))
    return w.masked_fill(~present, float(w[present].max())).float()


class UncertaintyMultiTask(UncertaintyMultiTaskCard, TaskLoss):
    """JS3C-Net eq. 2 (Kendall et al. 2018): L = sum_i 1/(2 sigma_i^2) L_i + log sigma_i.

    Parametrised by s_i = log sigma_i^2 (always finite, unlike the authors' raw sigma, seed_code.md §4):
    L = sum_i 0.5 * exp(-s_i) * L_i + 0.5 * s_i, over L_seg (point CE, unlabelled points ignored) and
    L_complet (voxel CE, invalid voxels ignored), each class-weighted by (max f / f_c)^(1/3) with the
    frequencies of the training split (the authors hard-code SemanticKITTI's counts). The s_i are
    trained with the student at 10x its learning rate, as the authors do (a default parameter group).
    """

    def __init__(self, params: _UncParams) -> None:
        super().__init__(params)
        self.log_var = nn.Parameter(torch.full((2,), float(params.init_log_var)))
        self.register_buffer("seg_weight", torch.ones(NUM_CLASSES))
        self.register_buffer("comp_weight", torch.ones(NUM_CLASSES))

    def prepare(self, train_set: Any) -> None:
        self.comp_weight = self.comp_weight.new_ones(self.num_classes)  # the data's class table's size
        self.seg_weight = self.seg_weight.new_ones(self.num_classes)
        if self.params.class_weights == "none":
            return
        from distilkit.data.stats import label_counts

        voxel, point = label_counts(train_set, self.num_classes)  # sized by the data's class table
        self.comp_weight = frequency_weights(voxel).to(self.comp_weight)
        seg = frequency_weights(point[1:])  # point class 0 = unlabelled (ignored)
        self.seg_weight = torch.cat([seg.new_zeros(1), seg]).to(self.seg_weight)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        # the labels of the points behind the point logits: a tap, as the model may keep a subset of points
        labels = taps["point_target"]
        seg_target = labels.masked_fill(labels == 0, IGNORE_INDEX)
        l_seg = cross_entropy(taps["points"], seg_target, weight=self.seg_weight)
        l_comp = cross_entropy(taps["student"], taps["target"], weight=self.comp_weight)
        s = self.log_var
        return 0.5 * torch.exp(-s[0]) * l_seg + 0.5 * s[0] + 0.5 * torch.exp(-s[1]) * l_comp + 0.5 * s[1]


class _ClassWeighted(ClassWeightedCard, TaskLoss):
    """A voxel loss with class weights from the training split's counts of ``COUNTED`` (computed once, in
    ``prepare``, over the labels the stage trains on: a label overlay's pseudo-labels, not the data's own)."""

    def __init__(self, params: _WeightedParams) -> None:
        super().__init__(params)
        self.register_buffer("weight", torch.ones(NUM_CLASSES))

    def prepare(self, train_set: Any) -> None:
        from distilkit.losses.ssc import class_weights

        try:  # sized by the data's class table
            w = class_weights(self.params.class_weights, train_set, self.num_classes, self.COUNTED, self.params.scale)
        except ValueError as exc:
            raise DistilkitError(str(exc)) from None
        self.weight = w.to(self.weight)


class WeightedCE(WeightedCECard, _ClassWeighted):
    """Class-weighted voxel CE (VoxFormer's Σ w_y ℓ / N_valid, or MonoScene's Σ w_y ℓ / Σ w_y)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.ssc import weighted_ce

        weight = self.weight if self.params.class_weights != "none" else None
        return weighted_ce(taps["student"], taps["target"], weight, self.params.normalize, self.ignore_index)


class PartialCE(PartialCECard, _ClassWeighted):
    """Scribble2Scene's partial CE (the Dean-Labeler's loss, eq. 1): the unweighted mean CE over the voxels a scribble
    labels with a class. Optional class weights count scribbles only, so the scribble setting never reads dense
    labels."""

    CHOICES = (
        Choice("class weights", "none: the unweighted mean over scribbled voxels", "eq. 1: unweighted",
               "the Dean-Labeler's training is not released", "`class_weights: log_frequency` (scribble counts)"),
    )

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.ssc import partial_ce

        weight = self.weight if self.params.class_weights != "none" else None
        return partial_ce(taps["student"], taps["target"], weight, self.ignore_index)


class GeometryWeightedCE(GeometryWeightedCECard, _ClassWeighted):
    """HASSC's geometry-weighted CE: w_y · CE · (1 + LGA) per valid voxel, the mean over each sample's valid voxels,
    then over the samples (``reduce``: the release's one sample per GPU; ``pooled``: over the batch's valid voxels),
    with LGA (the count of face neighbours with another label,
    :func:`~distilkit.losses.hardness.local_geometric_anisotropy`) derived from the labels the stage trains on."""

    CHOICES = (
        Choice("LGA", "derived from the training labels per batch: face neighbours (6) with another label; outside "
               "the volume or ignored: not counted", "local geometric anisotropy of the voxel's neighbourhood",
               "loaded from precomputed files (values 0-6) that the release does not ship the script for"),
        Choice("class weights", "10 / ln(f_c + 0.001) from the training split's counts",
               "class-weighted CE", "a table of 20 numbers: the same formula on SemanticKITTI's counts",
               "`class_weights: release`"),
        Choice("the batch reduction", "the mean of per-sample means (a sample without a valid voxel: 0)",
               "not stated", "one sample per GPU (samples_per_gpu=1), DDP averaging: the mean of per-sample means "
               "(each its valid voxels' mean)", "`reduce: pooled` (the batch's valid voxels pooled)"),
    )

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.hardness import geometry_weighted_ce, local_geometric_anisotropy

        target = taps["target"]
        weight = self.weight if self.params.class_weights != "none" else None
        lga = local_geometric_anisotropy(target, self.ignore_index)
        return geometry_weighted_ce(taps["student"], target, weight, lga, self.ignore_index, self.params.reduce)


class _VoxelLoss(VoxelLossCard, TaskLoss):
    """A parameterless loss ``FUNCTION(logits, target, ignore_index)`` of :mod:`distilkit.losses.ssc`."""

    FUNCTION = ""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses import ssc

        return getattr(ssc, self.FUNCTION)(taps["student"], taps["target"], self.ignore_index)


class GeoScal(GeoScalCard, _VoxelLoss):
    """MonoScene's geometry scene-class affinity loss (precision, recall, specificity of occupancy)."""

    FUNCTION = "geo_scal"


class SemScal(SemScalCard, _VoxelLoss):
    """MonoScene's semantic scene-class affinity loss (per present class: precision, recall, specificity)."""

    FUNCTION = "sem_scal"


class OccupancyCE(OccupancyCECard, TaskLoss):
    """VoxFormer's stage-1 loss: weighted two-class CE of the proposals against the pooled dense geometry."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.proposal import occupancy_ce

        return occupancy_ce(taps["student"], taps["target"], self.params.alpha, self.ignore_index)


class DepthL1(DepthL1Card, TaskLoss):
    """Depth regression of a camera model (metres, pixels with a true depth)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.proposal import depth_l1

        info = self.context.info if self.context is not None else None
        sparse = info is not None and bool(info.cameras) and info.cameras[0].depth == "sparse"
        return depth_l1(taps["student"], taps["target"], None if sparse else self.params.sky_depth)


class Chamfer(ChamferCard, TaskLoss):
    """Squared-L2 Chamfer distance between predicted points and the ground-truth scene (LiDiff's refinement loss):
    the evaluation ground truth ``scene_eval`` when the data has it (the untiled map crop), else ``scene``."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.structures import PointCloud

        return chamfer(taps["student"], PointCloud(taps["target"], taps["target_lengths"]))


# the parameters' models live with the cards (distilkit.cards.task_losses) and stay importable from here
__all__ = ["Chamfer", "DepthL1", "GeoScal", "GeometryWeightedCE", "NoParams", "OccupancyCE", "PartialCE", "SemScal",
           "TaskLoss", "UncertaintyMultiTask", "VoxelCE", "VoxelLovasz", "WeightedCE", "_CEParams", "_DepthParams",
           "_GeometryCEParams", "_LovaszParams", "_OccupancyParams", "_PartialParams", "_UncParams",
           "_WeightedCEParams", "_WeightedParams", "frequency_weights"]
