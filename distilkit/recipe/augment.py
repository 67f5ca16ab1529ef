"""``train.augment``: what a stage's training samples are drawn under (:mod:`distilkit.data.augment` applies it)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


class TiltSpec(BaseModel):
    """Small rotations about all three axes, each angle drawn from N(0, sigma²) and clipped to ±clip radians
    (LiDiff's ``rotate_perturbation_point_cloud``: sigma 0.06, clip 0.18)."""

    model_config = ConfigDict(extra="forbid")
    sigma: float = Field(0.06, ge=0, description="standard deviation of each angle (radians)")
    clip: float = Field(0.18, gt=0, description="each angle clipped to ±clip (radians)")


class AugmentSpec(BaseModel):
    """Training samples drawn under a random transform about the vertical axis, the same for every field of a
    sample, one per sample and step from the stage's seed (a resumed run draws the same).

    A **finite group** — ``flip`` and ``rotate90`` alone: JS3C-Net's ``{flip: [x, y], rotate90: z}`` — moves voxel
    grids exactly (voxels onto voxels), so any data takes it and a teacher's outputs under each of its transforms
    can be stored. ``rotate``, ``tilt`` and ``scale`` are **continuous** (LiDiff's and ScoreLiDAR's training
    transforms: a uniform turn about z, a small tilt, a scale in [0.95, 1.05], then a flip of y): they move points
    off any voxel grid, so only point-cloud data (``synthetic-scenes``) takes them."""

    model_config = ConfigDict(extra="forbid")
    flip: list[Literal["x", "y"]] = Field(default_factory=list, description="horizontal axes that may be flipped, "
                                                                           "each with probability 1/2")
    rotate90: Literal["z"] | None = Field(None, description="z: quarter turns about the vertical axis (needs a "
                                                            "grid square in x and y)")
    rotate: Literal["z"] | None = Field(None, description="z: a turn by a uniform angle about the vertical axis "
                                                          "(continuous; LiDiff's rotate_point_cloud)")
    tilt: TiltSpec | None = Field(None, description="small rotations about x, y and z (continuous; LiDiff's "
                                                    "rotate_perturbation_point_cloud: {sigma: 0.06, clip: 0.18})")
    scale: tuple[float, float] | None = Field(None, description="[low, high]: every coordinate times a factor "
                                                                "drawn uniformly (continuous; LiDiff: [0.95, 1.05])")

    @field_validator("flip")
    @classmethod
    def _once(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("give each axis once")
        return sorted(v)

    @model_validator(mode="after")
    def _scale(self) -> "AugmentSpec":
        if self.scale is not None and not 0 < self.scale[0] <= self.scale[1]:
            raise ValueError(f"scale: [low, high] with 0 < low <= high, got {list(self.scale)}")
        return self

    @property
    def continuous(self) -> bool:
        """Whether it draws from a continuum (then nothing can be stored per transform, and no grid follows it)."""
        return self.rotate is not None or self.tilt is not None or self.scale is not None


__all__ = ["AugmentSpec", "TiltSpec"]
