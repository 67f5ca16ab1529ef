"""The task losses' cards (torch-free): each supervised term's parameters, roles and registration; the
implementations (:mod:`distilkit.losses.task`, imported when a stage runs) subclass them."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import NoParams, TermCard
from distilkit.data.classes import IGNORE_INDEX
from distilkit.registry import TASK_LOSSES

_IMPL = "distilkit.losses.task"


class _CEParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ignore_index: int = IGNORE_INDEX


class VoxelCECard(TermCard):
    """Voxel cross entropy's declarations."""

    Params = _CEParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}


class _LovaszParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    classes: str = Field("present", pattern="^(present|all)$")
    ignore_index: int = IGNORE_INDEX


class VoxelLovaszCard(TermCard):
    """Lovász-softmax's declarations."""

    Params = _LovaszParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}


class _UncParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    init_log_var: float = Field(0.0, description="initial s = log sigma^2 of both tasks")
    class_weights: str = Field("auto", pattern="^(auto|none)$",
                               description="auto: (max f / f_c)^(1/3) from the training split's label frequencies "
                                           "(JS3C-Net); none: unweighted CE")


class UncertaintyMultiTaskCard(TermCard):
    """JS3C-Net's uncertainty-weighted multi-task loss's declarations."""

    Params = _UncParams
    CONSUMES = {"student": "voxel_logits", "points": "point_logits", "point_target": "point_labels"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_PARAM_GROUPS = [{"match": "log_var", "lr_scale": 10.0}]
    VERSION = 2  # 2: class weights, sigma at 10x the learning rate


class _WeightedParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    class_weights: Literal["none", "log_frequency"] = Field(
        "log_frequency", description="log_frequency: scale / ln(f_c + 0.001) from the training split's voxel counts "
                                     "(VoxFormer's, scale 10; a class never seen gets the largest weight); none")
    scale: float = Field(10.0, gt=0, description="VoxFormer 10, MonoScene 1")


class _WeightedCEParams(_WeightedParams):
    normalize: Literal["valid", "weight"] = Field("valid", description="divide by the valid voxels (VoxFormer) or by "
                                                                       "the sum of their weights (MonoScene)")


class ClassWeightedCard(TermCard):
    """A class-weighted voxel loss's declarations: ``COUNTED``, the batch field whose training-split counts give
    the class weights."""

    CONSUMES = {"student": "voxel_logits"}
    COUNTED: ClassVar[str] = "voxel_label"


class WeightedCECard(ClassWeightedCard):
    """Class-weighted voxel CE's declarations."""

    Params = _WeightedCEParams
    BATCH = {"target": "voxel_target"}


class _PartialParams(_WeightedParams):
    class_weights: Literal["none", "log_frequency"] = Field(
        "none", description="none: unweighted, as Scribble2Scene eq. 1 (default); log_frequency: scale / ln(f_c + "
                            "0.001) with f_c counted over the training split's scribbled voxels only (never the "
                            "dense labels)")


class PartialCECard(ClassWeightedCard):
    """Scribble2Scene's partial CE's declarations."""

    Params = _PartialParams
    BATCH = {"target": "scribble"}
    COUNTED = "scribble"
    VERSION = 2  # 2: unweighted by default (was: weights from the dense labels' counts)


class _GeometryCEParams(_WeightedParams):
    class_weights: Literal["none", "log_frequency", "release"] = Field(
        "log_frequency", description="log_frequency: scale / ln(f_c + 0.001) from the training split's voxel counts "
                                     "(the release's table is this formula on SemanticKITTI's counts); release: that "
                                     "table itself (20 classes); none")
    reduce: Literal["per_sample", "pooled"] = Field(
        "per_sample", description="the mean over each sample's valid voxels, then over the samples (the release: one "
                                  "sample per GPU, DDP averaging), or over the batch's valid voxels pooled (distilkit "
                                  "before v2)")


class GeometryWeightedCECard(ClassWeightedCard):
    """HASSC's geometry-weighted CE's declarations."""

    Params = _GeometryCEParams
    BATCH = {"target": "voxel_target"}
    VERSION = 2  # 2: per-sample means by default (was: the batch's valid voxels pooled)


class VoxelLossCard(TermCard):
    """A parameterless voxel loss's declarations (MonoScene's scene-class affinity losses)."""

    Params = NoParams
    CONSUMES = {"student": "voxel_logits"}
    BATCH = {"target": "voxel_target"}


class GeoScalCard(VoxelLossCard):
    """MonoScene's geometry scene-class affinity loss's declarations."""


class SemScalCard(VoxelLossCard):
    """MonoScene's semantic scene-class affinity loss's declarations."""


class _OccupancyParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    alpha: float = Field(0.54, gt=0, lt=1, description="weight of the occupied class (VoxFormer: 0.54)")


class OccupancyCECard(TermCard):
    """VoxFormer's stage-1 occupancy loss's declarations."""

    Params = _OccupancyParams
    CONSUMES = {"student": "occupancy_logits"}
    BATCH = {"target": "voxel_target"}


class _DepthParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sky_depth: float | None = Field(None, gt=0, description="pixels with no surface count as this far (metres; "
                                                            "e.g. the camera's max_depth); none: left out. Only "
                                                            "on dense depth maps: where the data's depth is sparse "
                                                            "LiDAR depth (a real folder), 0 means unknown and is "
                                                            "always left out")


class DepthL1Card(TermCard):
    """Depth regression's declarations."""

    Params = _DepthParams
    CONSUMES = {"student": "depth_map"}
    BATCH = {"target": "depth"}


class ChamferCard(TermCard):
    """The Chamfer-distance loss's declarations: the evaluation ground truth when the data has it."""

    Params = NoParams
    CONSUMES = {"student": "points"}
    BATCH = {"target": ("scene_eval", "scene"), "target_lengths": ("scene_eval_lengths", "scene_lengths")}


def _declare(name: str, cls: str, card: type[TermCard], **meta: Any) -> None:
    TASK_LOSSES.declare(name, f"{_IMPL}:{cls}", card=card, **meta)


_declare("ce", "VoxelCE", VoxelCECard, description="voxel cross entropy, ignore 255 and invalid voxels",
         paper="SCPNet eq. 4 (L_ce)", consumes=("voxel_logits",))
_declare("lovasz", "VoxelLovasz", VoxelLovaszCard, description="Lovász-softmax over classes present in the batch",
         paper="Berman et al. CVPR 2018; SCPNet eq. 4 (alpha = 1)", consumes=("voxel_logits",))
_declare("uncertainty_multitask", "UncertaintyMultiTask", UncertaintyMultiTaskCard,
         description="uncertainty-weighted point segmentation + completion CE (log-variance form)",
         paper="JS3C-Net eq. 2 (Kendall et al. CVPR 2018)", consumes=("voxel_logits", "point_logits", "point_labels"))

_declare("weighted_ce", "WeightedCE", WeightedCECard,
         description="class-weighted voxel CE, normalised by valid voxels or weights",
         paper="VoxFormer (Li et al. CVPR 2023); MonoScene (Cao & de Charette CVPR 2022)",
         consumes=("voxel_logits",))
_declare("hassc_ce", "GeometryWeightedCE", GeometryWeightedCECard,
         description="class-weighted voxel CE × (1 + local geometric anisotropy), the mean over each sample's valid "
                     "voxels, then over the samples",
         paper="HASSC (Wang et al. CVPR 2024), eq. of L_ssc with LGA; dense_heads/hassc_voxformer_head.py",
         consumes=("voxel_logits",))
_declare("partial_ce", "PartialCE", PartialCECard, description="CE over the voxels a scribble labels with a class",
         paper="Scribble2Scene (Wang et al. IJCAI 2024), Dean-Labeler", consumes=("voxel_logits",))
_declare("geo_scal", "GeoScal", GeoScalCard, description="scene-class affinity loss on geometry (occupancy)",
         paper="MonoScene (Cao & de Charette CVPR 2022), scene-class affinity loss", consumes=("voxel_logits",))
_declare("sem_scal", "SemScal", SemScalCard, description="scene-class affinity loss on semantics, per present class",
         paper="MonoScene (Cao & de Charette CVPR 2022), scene-class affinity loss", consumes=("voxel_logits",))
_declare("occupancy_ce", "OccupancyCE", OccupancyCECard,
         description="weighted empty/occupied CE at the proposals' resolution",
         paper="VoxFormer (Li et al. CVPR 2023), stage 1 (BCE_ssc_loss, alpha 0.54)", consumes=("occupancy_logits",))
_declare("depth_l1", "DepthL1", DepthL1Card, description="L1 depth error over pixels with a true depth",
         paper="VoxFormer (Li et al. CVPR 2023), stage 1 depth (stand-in for its stereo depth network)",
         consumes=("depth_map",))
_declare("chamfer", "Chamfer", ChamferCard,
         description="squared-L2 Chamfer distance to the ground-truth scene (both directions, per-set means summed)",
         paper="Nunes et al., LiDiff, CVPR 2024 (refinement; pytorch3d's chamfer_distance)", consumes=("points",))

__all__ = ["ChamferCard", "ClassWeightedCard", "DepthL1Card", "GeoScalCard", "GeometryWeightedCECard",
           "OccupancyCECard", "PartialCECard", "SemScalCard", "UncertaintyMultiTaskCard", "VoxelCECard",
           "VoxelLossCard", "VoxelLovaszCard", "WeightedCECard"]
