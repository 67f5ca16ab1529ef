"""Registered task losses (supervised terms of a stage): CE, Lovász-softmax, uncertainty weighting."""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX, NUM_CLASSES
from distilkit.losses.chamfer import chamfer
from distilkit.losses.segmentation import cross_entropy, lovasz_softmax
from distilkit.errors import DistilkitError
from distilkit.registry import TASK_LOSSES, NoParams
from distilkit.term import Term


class TaskLoss(Term):
    """A supervised term (:class:`~distilkit.term.Term` with no teacher role): its targets are batch roles."""


class _CEParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ignore_index: int = IGNORE_INDEX


class VoxelCE(TaskLoss):
    """Cross entropy on voxel logits against ``voxel_target`` (invalid voxels ignored)."""

    Params = _CEParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return cross_entropy(taps["student"], taps["target"], self.params.ignore_index)


class _LovaszParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    classes: str = Field("present", pattern="^(present|all)$")
    ignore_index: int = IGNORE_INDEX


class VoxelLovasz(TaskLoss):
    """Lovász-softmax on voxel logits (SCPNet eq. 4, alpha term)."""

    Params = _LovaszParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return lovasz_softmax(taps["student"], taps["target"], self.params.ignore_index, self.params.classes)


class _UncParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    init_log_var: float = Field(0.0, description="initial s = log sigma^2 of both tasks")
    class_weights: str = Field("auto", pattern="^(auto|none)$",
                               description="auto: (max f / f_c)^(1/3) from the training split's label frequencies "
                                           "(JS3C-Net); none: unweighted CE")


def frequency_weights(counts: Tensor, power: float = 1.0 / 3.0) -> Tensor:
    """JS3C-Net's class weights (max_c f_c / f_c)^(1/3); a class that never occurs gets the largest weight."""
    counts = counts.double()
    present = counts > 0
    if not bool(present.any()):
        return torch.ones_like(counts, dtype=torch.float32)
    f = counts / counts.sum()
    w = torch.where(present, (f.max() / f.clamp_min(1e-30)) ** power, torch.zeros_like(f))
    return w.masked_fill(~present, float(w[present].max())).float()


class UncertaintyMultiTask(TaskLoss):
    """JS3C-Net eq. 2 (Kendall et al. 2018): L = sum_i 1/(2 sigma_i^2) L_i + log sigma_i.

    Parametrised by s_i = log sigma_i^2 (always finite, unlike the authors' raw sigma, seed_code.md §4):
    L = sum_i 0.5 * exp(-s_i) * L_i + 0.5 * s_i, over L_seg (point CE, unlabelled points ignored) and
    L_complet (voxel CE, invalid voxels ignored), each class-weighted by (max f / f_c)^(1/3) with the
    frequencies of the training split (the authors hard-code SemanticKITTI's counts). The s_i are
    trained with the student at 10x its learning rate, as the authors do (a default parameter group).
    """

    Params = _UncParams
    CONSUMES = {"student": "voxel_logits", "points": "point_logits", "point_target": "point_labels"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_PARAM_GROUPS = [{"match": "log_var", "lr_scale": 10.0}]
    VERSION = 2  # 2: class weights, sigma at 10x the learning rate

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


class _WeightedParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    class_weights: Literal["none", "log_frequency"] = Field(
        "log_frequency", description="log_frequency: scale / ln(f_c + 0.001) from the training split's voxel counts "
                                     "(VoxFormer's, scale 10; a class never seen gets the largest weight); none")
    scale: float = Field(10.0, gt=0, description="VoxFormer 10, MonoScene 1")


class _WeightedCEParams(_WeightedParams):
    normalize: Literal["valid", "weight"] = Field("valid", description="divide by the valid voxels (VoxFormer) or by "
                                                                       "the sum of their weights (MonoScene)")


class _ClassWeighted(TaskLoss):
    """A voxel loss with class weights from the training split's counts of ``COUNTED`` (computed once, in
    ``prepare``, over the labels the stage trains on: a label overlay's pseudo-labels, not the data's own)."""

    CONSUMES = {"student": "voxel_logits"}
    COUNTED = "voxel_label"

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


class WeightedCE(_ClassWeighted):
    """Class-weighted voxel CE (VoxFormer's Σ w_y ℓ / N_valid, or MonoScene's Σ w_y ℓ / Σ w_y)."""

    Params = _WeightedCEParams
    BATCH = {"target": "voxel_target"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.ssc import weighted_ce

        weight = self.weight if self.params.class_weights != "none" else None
        return weighted_ce(taps["student"], taps["target"], weight, self.params.normalize, self.ignore_index)


class _PartialParams(_WeightedParams):
    class_weights: Literal["none", "log_frequency"] = Field(
        "none", description="none: unweighted, as Scribble2Scene eq. 1 (default); log_frequency: scale / ln(f_c + "
                            "0.001) with f_c counted over the training split's scribbled voxels only (never the "
                            "dense labels)")


class PartialCE(_ClassWeighted):
    """Scribble2Scene's partial CE (the Dean-Labeler's loss, eq. 1): the unweighted mean CE over the voxels a scribble
    labels with a class. Optional class weights count scribbles only, so the scribble setting never reads dense
    labels."""

    CHOICES = (
        Choice("class weights", "none: the unweighted mean over scribbled voxels", "eq. 1: unweighted",
               "the Dean-Labeler's training is not released", "`class_weights: log_frequency` (scribble counts)"),
    )

    Params = _PartialParams
    BATCH = {"target": "scribble"}
    COUNTED = "scribble"
    VERSION = 2  # 2: unweighted by default (was: weights from the dense labels' counts)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.ssc import partial_ce

        weight = self.weight if self.params.class_weights != "none" else None
        return partial_ce(taps["student"], taps["target"], weight, self.ignore_index)


class _GeometryCEParams(_WeightedParams):
    class_weights: Literal["none", "log_frequency", "release"] = Field(
        "log_frequency", description="log_frequency: scale / ln(f_c + 0.001) from the training split's voxel counts "
                                     "(the release's table is this formula on SemanticKITTI's counts); release: that "
                                     "table itself (20 classes); none")
    reduce: Literal["per_sample", "pooled"] = Field(
        "per_sample", description="the mean over each sample's valid voxels, then over the samples (the release: one "
                                  "sample per GPU, DDP averaging), or over the batch's valid voxels pooled (distilkit "
                                  "before v2)")


class GeometryWeightedCE(_ClassWeighted):
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
    Params = _GeometryCEParams
    BATCH = {"target": "voxel_target"}
    VERSION = 2  # 2: per-sample means by default (was: the batch's valid voxels pooled)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.hardness import geometry_weighted_ce, local_geometric_anisotropy

        target = taps["target"]
        weight = self.weight if self.params.class_weights != "none" else None
        lga = local_geometric_anisotropy(target, self.ignore_index)
        return geometry_weighted_ce(taps["student"], target, weight, lga, self.ignore_index, self.params.reduce)


class _VoxelLoss(TaskLoss):
    """A parameterless loss ``FUNCTION(logits, target, ignore_index)`` of :mod:`distilkit.losses.ssc`."""

    Params = NoParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    FUNCTION = ""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses import ssc

        return getattr(ssc, self.FUNCTION)(taps["student"], taps["target"], self.ignore_index)


class GeoScal(_VoxelLoss):
    """MonoScene's geometry scene-class affinity loss (precision, recall, specificity of occupancy)."""

    FUNCTION = "geo_scal"


class SemScal(_VoxelLoss):
    """MonoScene's semantic scene-class affinity loss (per present class: precision, recall, specificity)."""

    FUNCTION = "sem_scal"


TASK_LOSSES.add("ce", VoxelCE, description="voxel cross entropy, ignore 255 and invalid voxels",
                paper="SCPNet eq. 4 (L_ce)", consumes=("voxel_logits",))
TASK_LOSSES.add("lovasz", VoxelLovasz, description="Lovász-softmax over classes present in the batch",
                paper="Berman et al. CVPR 2018; SCPNet eq. 4 (alpha = 1)", consumes=("voxel_logits",))
TASK_LOSSES.add("uncertainty_multitask", UncertaintyMultiTask,
                description="uncertainty-weighted point segmentation + completion CE (log-variance form)",
                paper="JS3C-Net eq. 2 (Kendall et al. CVPR 2018)", consumes=("voxel_logits", "point_logits", "point_labels"))

TASK_LOSSES.add("weighted_ce", WeightedCE, description="class-weighted voxel CE, normalised by valid voxels or weights",
                paper="VoxFormer (Li et al. CVPR 2023); MonoScene (Cao & de Charette CVPR 2022)",
                consumes=("voxel_logits",))
TASK_LOSSES.add("hassc_ce", GeometryWeightedCE, description="class-weighted voxel CE × (1 + local geometric "
                "anisotropy), the mean over each sample's valid voxels, then over the samples", paper="HASSC (Wang et al. CVPR 2024), eq. of L_ssc with LGA; "
                "dense_heads/hassc_voxformer_head.py", consumes=("voxel_logits",))
TASK_LOSSES.add("partial_ce", PartialCE, description="CE over the voxels a scribble labels with a class",
                paper="Scribble2Scene (Wang et al. IJCAI 2024), Dean-Labeler", consumes=("voxel_logits",))
TASK_LOSSES.add("geo_scal", GeoScal, description="scene-class affinity loss on geometry (occupancy)",
                paper="MonoScene (Cao & de Charette CVPR 2022), scene-class affinity loss", consumes=("voxel_logits",))
TASK_LOSSES.add("sem_scal", SemScal, description="scene-class affinity loss on semantics, per present class",
                paper="MonoScene (Cao & de Charette CVPR 2022), scene-class affinity loss", consumes=("voxel_logits",))


class _OccupancyParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    alpha: float = Field(0.54, gt=0, lt=1, description="weight of the occupied class (VoxFormer: 0.54)")


class OccupancyCE(TaskLoss):
    """VoxFormer's stage-1 loss: weighted two-class CE of the proposals against the pooled dense geometry."""

    Params = _OccupancyParams
    CONSUMES = {"student": "occupancy_logits"}
    BATCH = {"target": "voxel_target"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.proposal import occupancy_ce

        return occupancy_ce(taps["student"], taps["target"], self.params.alpha, self.ignore_index)


class _DepthParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sky_depth: float | None = Field(None, gt=0, description="pixels with no surface count as this far (metres; "
                                                            "e.g. the camera's max_depth); none: left out. Only "
                                                            "on dense depth maps: where the data's depth is sparse "
                                                            "LiDAR depth (a real folder), 0 means unknown and is "
                                                            "always left out")


class DepthL1(TaskLoss):
    """Depth regression of a camera model (metres, pixels with a true depth)."""

    Params = _DepthParams
    CONSUMES = {"student": "depth_map"}
    BATCH = {"target": "depth"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.losses.proposal import depth_l1

        info = self.context.info if self.context is not None else None
        sparse = info is not None and bool(info.cameras) and info.cameras[0].depth == "sparse"
        return depth_l1(taps["student"], taps["target"], None if sparse else self.params.sky_depth)


TASK_LOSSES.add("occupancy_ce", OccupancyCE, description="weighted empty/occupied CE at the proposals' resolution",
                paper="VoxFormer (Li et al. CVPR 2023), stage 1 (BCE_ssc_loss, alpha 0.54)",
                consumes=("occupancy_logits",))
TASK_LOSSES.add("depth_l1", DepthL1, description="L1 depth error over pixels with a true depth",
                paper="VoxFormer (Li et al. CVPR 2023), stage 1 depth (stand-in for its stereo depth network)",
                consumes=("depth_map",))



class Chamfer(TaskLoss):
    """Squared-L2 Chamfer distance between predicted points and the ground-truth scene (LiDiff's refinement loss):
    the evaluation ground truth ``scene_eval`` when the data has it (the untiled map crop), else ``scene``."""

    Params = NoParams
    CONSUMES = {"student": "points"}
    BATCH = {"target": ("scene_eval", "scene"), "target_lengths": ("scene_eval_lengths", "scene_lengths")}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.structures import PointCloud

        return chamfer(taps["student"], PointCloud(taps["target"], taps["target_lengths"]))


TASK_LOSSES.add("chamfer", Chamfer, description="squared-L2 Chamfer distance to the ground-truth scene (both "
                                                "directions, per-set means summed)",
                paper="Nunes et al., LiDiff, CVPR 2024 (refinement; pytorch3d's chamfer_distance)", consumes=("points",))
