"""Types shared by the objectives' parameters (torch-free; re-exported by :mod:`distilkit.objectives.common`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

MaskName = Literal["all", "valid", "occupied"]


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


__all__ = ["MaskName", "NoParams"]
