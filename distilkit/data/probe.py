"""Smaller copies of a data set for measuring what a training step costs before anything is trained.

A dataset registers ``probe=`` (a function of its parameters returning a :class:`ProbePlan`): the same data at
one or two small sizes, one training sample each, the size of each on one scale (voxels of the grid, points of a
cloud) and the recipe's own size on it. :mod:`distilkit.engine.memory.estimate` runs one training step at each probe size
and extrapolates to the recipe's size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel


@dataclass(frozen=True)
class ProbePlan:
    """``probes``: (parameters of a small copy of the data, its size); ``target``: the recipe's size on the same
    scale; ``unit``: what size counts (``voxels``); ``describe``: the recipe's size in words (``a 256x256x32 grid``)."""

    probes: list[tuple[BaseModel, float]]
    target: float
    unit: str
    describe: str


def _one_scene(params: BaseModel, **update: Any) -> BaseModel:
    counts = {k: 1 for k in ("num_train", "num_val", "num_test") if k in type(params).model_fields}
    return params.model_copy(update={**counts, **update})


def grid_plan(params: BaseModel) -> ProbePlan:
    """Voxel data (``scale`` coarsens the 256x256x32 SemanticKITTI grid): measured at the recipe's own grid when
    it has at most 128x128x16 voxels, else at 64x64x8 and 128x128x16 and extrapolated linearly in the voxels."""
    def voxels(scale: int) -> float:
        return float((256 // scale) * (256 // scale) * (32 // scale))

    scale = int(getattr(params, "scale"))
    scales = [scale] if scale >= 2 else [4, 2]
    return ProbePlan([(_one_scene(params, scale=s), voxels(s)) for s in scales], voxels(scale), "voxels",
                     f"a {256 // scale}x{256 // scale}x{32 // scale} grid")


def cloud_plan(params: BaseModel) -> ProbePlan:
    """Point clouds of a fixed size: measured at the recipe's own size (one scene)."""
    points = float(getattr(params, "scene_points"))
    return ProbePlan([(_one_scene(params), points)], points, "points",
                     f"{int(points):,} scene points and {getattr(params, 'scan_points'):,} scan points")


__all__ = ["ProbePlan", "cloud_plan", "grid_plan"]
