"""ScoreLiDAR's structural loss (eq. 12-17) as an objective: the student's samples against the ground-truth scene,
with the ground truth's key points computed once per scene and cached."""

from __future__ import annotations

from typing import Any

import torch
from pydantic import BaseModel
from torch import Tensor

from distilkit.cards.objectives.structural import StructuralCard, StructuralParams
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.structural import point_wise, scene_wise, select_keypoints
from distilkit.objectives.base import MultiTapObjective
from distilkit.structures import PointCloud


class Structural(StructuralCard, MultiTapObjective):
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


__all__ = ["Structural", "StructuralParams"]
