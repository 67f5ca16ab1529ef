"""ScoreLiDAR's structural loss (eq. 12-17) as an objective: the student's samples against the ground-truth scene,
with the ground truth's key points computed once per scene and cached."""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.structural import point_wise, scene_wise, select_keypoints
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.structures import PointCloud


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


class Structural(MultiTapObjective):
    """lambda_scene * scene_wise + lambda_point * point_wise between the student's samples and the scene (eq. 17).

    Key points depend on the ground truth only: with ``keypoints: per-step`` (the released code) a new random sample
    is drawn every step from the stage's random stream; with ``cached`` they are selected once per ``scene_id`` (the
    batch's meta) with a generator seeded from the id, and reused every step."""

    CHOICES = (
        Choice("scene-wise term", "each generated point to its nearest ground-truth point (eq. 12 as described)",
               "eq. 12: a scene-wise distance to the ground truth", "F.mse_loss between index-aligned points of two "
               "unordered sets (pulls every point to the centroid)", "`legacy_index_aligned: true`"),
        Choice("key points", "drawn anew every step (the release)", "§4.2: the top 1/3 by curvature of a 1/10 sample",
               "randperm every step, curvature in a Python loop", "`keypoints: cached` (once per scene)"),
    )

    Params = StructuralParams
    CONSUMES = {"student": "points"}
    TEACHER_ROLES = frozenset()
    BATCH = {"target": "scene", "target_lengths": "scene_lengths"}

    def __init__(self, params: BaseModel) -> None:
        super().__init__(params)
        self._keys: dict[str, Tensor] = {}

    def keypoints(self, scene: Tensor, scene_id: str) -> Tensor:
        p = self.params
        if p.keypoints == "per-step":
            return select_keypoints(scene.detach(), p.k, p.sample_ratio, p.keep_ratio)
        if scene_id and scene_id in self._keys:
            return self._keys[scene_id].to(scene.device)
        seed = int.from_bytes(scene_id.encode()[-8:].rjust(8, b"\0"), "little") % (2**63) if scene_id else 0
        key = select_keypoints(scene.detach(), p.k, p.sample_ratio, p.keep_ratio, torch.Generator().manual_seed(seed))
        if scene_id:
            self._keys[scene_id] = key.cpu()
        return key

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        samples: PointCloud = taps["student"]
        target = PointCloud(taps["target"], taps["target_lengths"])
        ids = batch.meta.get("scene_id") or [""] * batch.size
        keys = [self.keypoints(target.cloud(b), ids[b]) for b in range(batch.size)]
        p = self.params
        return (p.lambda_scene * scene_wise(samples, target, p.legacy_index_aligned, p.scene_reduction)
                + p.lambda_point * point_wise(samples, target, keys))


register_objective("structural", Structural, description="ScoreLiDAR's structural loss: nearest-point scene term + "
                                                         "key-point distance-matrix term against the ground truth",
                   paper="ScoreLiDAR (Zhang et al., ICCV 2025), eq. 12-17",
                   equation="λ_scene mean_i min_j ‖g_i − p_j‖² + λ_point mean ‖D − D_G‖², key points = top 1/3 "
                            "curvature of a 1/10 sample",
                   shapes="student samples: points (B, M, 3); target: the batch's scene (B, N, 3) + lengths")
