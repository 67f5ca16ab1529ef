"""Card of ScoreLiDAR's structural loss, eq. 12-17 (:mod:`distilkit.objectives.structural`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import ObjectiveCard, declare_objective


class StructuralParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    lambda_scene: float = Field(0.5, ge=0, description="weight of the scene-wise term (eq. 17)")
    lambda_point: float = Field(0.01, ge=0, description="weight of the point-wise term (eq. 17)")
    k: int = Field(180, ge=1, description="neighbours of the curvature (eq. 13-15)")
    sample_ratio: float = Field(0.1, gt=0, le=1, description="share of the scene sampled before the curvature")
    keep_ratio: float = Field(1 / 3, gt=0, le=1, description="share of the sample kept as key points")
    legacy_index_aligned: bool = Field(False, description="the released code's index-aligned scene-wise MSE")
    scene_reduction: Literal["mean", "sum"] = Field(
        "mean", description="scene-wise term: mean over points and xyz (the released code's MSE, what lambda_scene = "
                            "0.5 was tuned with) or summed over xyz (eq. 12's squared norm, 3x larger)")
    keypoints: Literal["per-step", "cached"] = Field(
        "per-step", description="key points drawn anew at every step (the released code) or once per scene and "
                                "cached (faster: the curvature depends on the ground truth only)")


class StructuralCard(ObjectiveCard):
    """ScoreLiDAR's structural loss against the ground-truth scene (card of
    :class:`distilkit.objectives.structural.Structural`)."""

    Params = StructuralParams
    TAP_HINTS = {"student": ("samples",)}
    CONSUMES = {"student": "points"}
    TEACHER_ROLES = frozenset()
    BATCH = {"target": "scene", "target_lengths": "scene_lengths"}


declare_objective("structural", "distilkit.objectives.structural:Structural", StructuralCard,
                  description="ScoreLiDAR's structural loss: nearest-point scene term + key-point distance-matrix term "
                              "against the ground truth",
                  paper="ScoreLiDAR (Zhang et al., ICCV 2025), eq. 12-17",
                  equation="λ_scene mean_i min_j ‖g_i − p_j‖² + λ_point mean ‖D − D_G‖², key points = top 1/3 "
                           "curvature of a 1/10 sample",
                  shapes="student samples: points (B, M, 3); target: the batch's scene (B, N, 3) + lengths")

__all__ = ["StructuralCard", "StructuralParams"]
