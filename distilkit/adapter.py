"""The adapter contract: how distilkit sees a teacher or student model.

An adapter is an ``nn.Module`` registered in :data:`distilkit.registry.ADAPTERS`. It declares

* ``Params``: a pydantic model of its constructor parameters (validated when a recipe loads);
* ``TAPS``: tap name -> tap kind (see :mod:`distilkit.taps`) that ``forward`` returns;
* ``LOGITS_TAP``: the ``voxel_logits`` tap that predictions and evaluation use;
* ``DEFAULT_TASK_LOSSES``: task losses used when a recipe stage names none;
* ``VERSION``: bump it when the model's behaviour changes, so that stages using it retrain.

``forward(batch)`` takes the collated batch (:func:`distilkit.data.datasets.collate`) and returns
a dict with (at least) every declared tap.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from pydantic import BaseModel, ConfigDict
from torch import Tensor, nn

from distilkit.data.datasets import DataInfo


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Adapter(nn.Module, ABC):
    Params: ClassVar[type[BaseModel]] = NoParams
    TAPS: ClassVar[dict[str, str]] = {}
    LOGITS_TAP: ClassVar[str] = "logits"
    DEFAULT_TASK_LOSSES: ClassVar[list[dict[str, Any]]] = [{"name": "ce", "weight": 1.0}]
    VERSION: ClassVar[int] = 1

    def __init__(self, params: BaseModel, info: DataInfo) -> None:
        super().__init__()
        self.params = params
        self.info = info

    @abstractmethod
    def forward(self, batch: dict[str, Tensor]) -> dict[str, Any]:
        """Run the model on a collated batch; return every declared tap."""

    @torch.no_grad()
    def predict(self, outputs: dict[str, Any]) -> Tensor:
        """(B, X, Y, Z) class ids from the logits tap."""
        return outputs[self.LOGITS_TAP].argmax(dim=1)

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> tuple[int, ...] | None:
        """The voxel grid (X, Y, Z) a voxel tap lives on, known before training (default: the data's
        SSC grid); None for taps that are not on a voxel grid. ``validate`` checks alignments with it."""
        if cls.TAPS.get(tap) in ("sparse_features", "voxel_logits"):
            return tuple(info.grid.shape)
        return None

    @classmethod
    def taps_of_kind(cls, kind: str) -> list[str]:
        return [name for name, k in cls.TAPS.items() if k == kind]


def select_frames(batch: dict[str, Tensor], frames: int) -> dict[str, Tensor]:
    """Keep the points of the first ``frames`` scans (frame offset < frames)."""
    keep = batch["point_frame"] < frames
    out = dict(batch)
    for k in ("points", "point_batch", "point_frame", "point_label"):
        out[k] = batch[k][keep]
    return out
