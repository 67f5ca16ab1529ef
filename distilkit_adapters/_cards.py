"""What the built-in adapters share in their cards (torch-free, see :mod:`distilkit.cards`): the refusal of a field
of the other ``size``, and the declarations of an adapter on fused LiDAR scans."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel

from distilkit.cards.base import AdapterCard
from distilkit.data.camera import CAMERA_INPUTS
from distilkit.data.info import DataInfo
from distilkit.data.lidar import LIDAR_INPUTS, frames_problems


def fields_of_one_size(params: BaseModel, only: dict[str, tuple[str, ...]]) -> None:
    """Refuse a field the recipe set, away from its default, for the other ``size`` (``only``: each size's fields that
    the other one does not read) — it would be ignored without a word (e.g. ``channels: 16`` with ``size: paper``,
    whose widths are the release's). A default written out (a saved checkpoint's parameters) passes."""
    size = getattr(params, "size")
    fields = type(params).model_fields
    for other, names in only.items():
        given = [n for n in names if n in params.model_fields_set
                 and getattr(params, n) != fields[n].get_default(call_default_factory=True)]
        if other != size and given:
            raise ValueError(f"{', '.join(given)} {'is' if len(given) == 1 else 'are'} read by size {other} only; "
                             f"size {size} does not use {'it' if len(given) == 1 else 'them'} (remove "
                             f"{'it' if len(given) == 1 else 'them'}, or set size: {other})")


class MultiFrameLidarCard(AdapterCard):
    """An adapter on LiDAR points with a ``frames`` parameter (scans fused): declares the LiDAR inputs,
    rejects more frames than the data has, and shows "N frames" in the results table."""

    INPUTS = LIDAR_INPUTS

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        return frames_problems(params, info)

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        frames = int(getattr(params, "frames"))
        return f"{frames} frame{'s' if frames > 1 else ''}"
