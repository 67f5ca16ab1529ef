"""``teacher.store``: the frozen teacher's outputs written once and read by every student that shares them
(:mod:`distilkit.engine.store.teacher_outputs` is the format, :mod:`distilkit.engine.train.teacher_store` the
build)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class StoreSpec(BaseModel):
    """How the teacher's outputs are stored. The one layout today is the exact one: every value of every tap the
    stage's terms read, in float32, so a student trained from the store equals the student trained with the live
    teacher bit for bit."""

    model_config = ConfigDict(extra="forbid")
    precision: Literal["float32"] = Field("float32", description="the stored values' type: float32 (exact)")
    shard: int = Field(16, ge=1, description="samples per shard file (each file written whole, then renamed)")


__all__ = ["StoreSpec"]
