"""``teacher.store``: the frozen teacher's outputs written once and read by every student that shares them
(:mod:`distilkit.engine.store.teacher_outputs` is the format, :mod:`distilkit.engine.train.teacher_store` the
build)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class StoreSpec(BaseModel):
    """How the teacher's outputs are stored. The default layout is the exact one: every value of every tap the
    stage's terms read, in float32, so a student trained from the store equals the student trained with the live
    teacher bit for bit. The other layouts are opt-in and lossy, each measured in docs/how-to/memory.md: a narrower
    ``precision``; only the ``voxels`` the terms' masks read (``validate`` refuses it for a term that reads more);
    the ``topk`` class scores of each voxel with the rest's probability mass (refused for a term that reads more than
    the teacher's softmax)."""

    model_config = ConfigDict(extra="forbid")
    precision: Literal["float32", "float16", "bfloat16"] = Field(
        "float32", description="the stored values' type: float32 (exact), float16 or bfloat16 (half the bytes; read "
                               "back as float32)")
    voxels: Literal["all", "valid", "occupied"] = Field(
        "all", description="the voxels kept of each dense tap on the labels' grid: all (exact), valid (label != "
                           "ignore) or occupied (valid and not empty), chosen by the labels the stage's terms read; "
                           "the others read back as 0")
    topk: int | None = Field(None, ge=1, description="keep only the k largest class scores of each voxel of a "
                                                     "voxel_logits tap and the rest's probability mass (spread evenly "
                                                     "over the other classes on reading); None: every class")
    shard: int = Field(16, ge=1, description="samples per shard file (each file written whole, then renamed)")

    @property
    def exact(self) -> bool:
        """Whether this layout keeps every value as the teacher computed it."""
        return self.precision == "float32" and self.voxels == "all" and self.topk is None


__all__ = ["StoreSpec"]
