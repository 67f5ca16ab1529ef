"""Card of the voxel-to-BEV distillation (Jiang et al., arXiv 2304.11393: Cylinder3D into PolarNet)
(:mod:`distilkit.objectives.bev`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective


class BEVParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    collapse: Literal["max", "mean"] = Field("max", description="the teacher's voxels reduced over each column: max "
                                                                "(the release's scatter-max) or mean")
    adapter: Literal["release", "none"] = Field(
        "release", description="release: the teacher's collapsed map through BatchNorm, a 3x3 convolution to the "
                               "student's channels, ReLU, BatchNorm, trained with the student (the target is not "
                               "detached); none: the map as it is (one channel count)")
    weighting: Literal["labels", "none"] = Field(
        "labels", description="labels: each cell weighted by its column's class weights, sum over channels, "
                              "mean, square root (LWD); none: the plain mean squared error (VPD)")
    root: bool = Field(True, description="with labels: the square root of the weighted mean (the release)")


class BEVCard(ObjectiveCard):
    """The voxel-to-BEV term (card of :class:`distilkit.objectives.bev.VoxelToBEV`), weight 2."""

    Params = BEVParams
    MATCH = {"teacher": Match("own", "collapsed", on_labels=True)}

    @classmethod
    def match(cls, params: BaseModel | None = None) -> dict[str, Match]:
        """The release's adapter projects the teacher's plane (``adapter: none``: equal widths); the class weights
        pool the labels to the map (``weighting: none``: any plane)."""
        own = params is None or getattr(params, "adapter") == "release"
        labels = params is None or getattr(params, "weighting") == "labels"
        return {"teacher": Match("own" if own else "equal", "collapsed", on_labels=labels)}
    CONSUMES = {"student": "bev_features", "teacher": "sparse_features"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 2.0


declare_objective("bev_from_voxels", "distilkit.objectives.bev:VoxelToBEV", BEVCard,
                  description="voxel-to-BEV: the teacher's voxels max-pooled over height, adapted, against a BEV "
                              "student by a label-weighted distance",
                  paper="Jiang et al., arXiv 2304.11393 (Cylinder3D to PolarNet), kd/weight_mse.py",
                  equation="sqrt(mean_{b,i,j} W_bij Σ_c (A(max_z f_T) − f_S)^2), W = Σ_z α_label / 50",
                  shapes="(B, C_s, X, Y) student map, sparse teacher voxels on the same (X, Y) plane")

__all__ = ["BEVCard", "BEVParams"]
