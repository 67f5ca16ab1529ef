"""Connectors: learnable projections of a student tap to the teacher tap's channels, generic over kinds.

Declared per objective in a recipe (``{name: pkt, connector: linear}``) or by an objective's
``DEFAULT_CONNECTOR`` (FitNets: its 1x1 regressor is the ``linear`` connector). Sized from the first
batch, trained with the student, saved with its checkpoints. ``linear`` is a 1x1 convolution on
(B, C, *S) maps and a linear layer on (N, C) rows or on the features of sparse voxels.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

from distilkit.errors import TapError
from distilkit.objectives.common import conv1x1
from distilkit.taps import SparseVoxels

CONNECTOR_TYPES = ("linear",)


def _channels(value: Any) -> tuple[int, int]:
    """(channels, spatial dims) of a tap value a connector can project."""
    if isinstance(value, SparseVoxels):
        return value.feats.shape[1], 0
    if isinstance(value, Tensor) and value.dim() >= 2:
        return value.shape[1], value.dim() - 2
    raise TapError(f"a connector projects feature maps, (N, C) rows or sparse voxels, got {type(value).__name__}")


class Connector(nn.Module):
    """``linear``: student channels -> teacher channels, built from one pair of tap values."""

    def __init__(self, kind: str, student: Any, teacher: Any) -> None:
        super().__init__()
        if kind not in CONNECTOR_TYPES:
            raise ValueError(f"unknown connector {kind!r} (known: {', '.join(CONNECTOR_TYPES)})")
        (cs, dims), (ct, _) = _channels(student), _channels(teacher)
        self.proj = conv1x1(cs, ct, dims) if dims in (2, 3) else nn.Linear(cs, ct)

    def forward(self, value: Any) -> Any:
        if isinstance(value, SparseVoxels):
            return value.with_feats(self.proj(value.feats))
        return self.proj(value)
