"""Connectors: learnable projections of a student tap to the teacher tap's channels, generic over kinds, from the
``CONNECTORS`` registry (plugins add their own).

Declared per objective in a recipe (``{name: pkt, connector: linear}``) or by an objective's
``DEFAULT_CONNECTOR`` (FitNets: its 1x1 regressor is the ``linear`` connector). Sized from the first
batch, trained with the student, saved with its checkpoints. A registered connector is
``build(student_channels, teacher_channels, spatial_dims) -> nn.Module`` acting on ``(B, C, *S)`` maps (``dims`` 2
or 3) or on (N, C) rows (``dims`` 0: rows, and the features of sparse voxels). Built in: ``linear`` (also
``conv1x1``: a 1x1 convolution on maps, a linear layer on rows), ``mlp`` (two of them with a ReLU between, as wide
as the wider side), ``conv3`` (a 3x3(x3) convolution on maps, for spatial context) and ``height_max`` /
``height_mean`` (voxel features collapsed over height onto the bird's-eye plane, then ``linear``: a 3-D student
against a BEV teacher), declared in ``distilkit.cards.connectors``.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

from distilkit.errors import TapError
from distilkit.objectives.common import conv1x1
from distilkit.registry import CONNECTORS
from distilkit.structures import SparseVoxels


def _channels(value: Any) -> tuple[int, int]:
    """(channels, spatial dims) of a tap value a connector can project."""
    if isinstance(value, SparseVoxels):
        return value.feats.shape[1], 0
    if isinstance(value, Tensor) and value.dim() >= 2:
        return value.shape[1], value.dim() - 2
    raise TapError(f"a connector projects feature maps, (N, C) rows or sparse voxels, got {type(value).__name__}")


def _linear(cs: int, ct: int, dims: int) -> nn.Module:
    return conv1x1(cs, ct, dims) if dims in (2, 3) else nn.Linear(cs, ct)


def _mlp(cs: int, ct: int, dims: int) -> nn.Module:
    hidden = max(cs, ct)
    return nn.Sequential(_linear(cs, hidden, dims), nn.ReLU(inplace=True), _linear(hidden, ct, dims))


def _conv3(cs: int, ct: int, dims: int) -> nn.Module:
    if dims not in (2, 3):
        raise TapError("connector conv3 needs a dense feature map (B, C, H, W) or (B, C, X, Y, Z); use linear or mlp "
                       "for rows and sparse voxels")
    return (nn.Conv3d if dims == 3 else nn.Conv2d)(cs, ct, 3, padding=1)


class HeightCollapse(nn.Module):
    """A volume or sparse voxels collapsed over height onto the (X, Y) plane (max or mean per channel,
    :func:`~distilkit.losses.collapse_height`), then a 1x1 convolution to the other side's channels: a 3-D
    student's features against a bird's-eye teacher map. Takes the tap's whole value."""

    whole = True  # the Connector hands it the value itself (sparse voxels: not only their features)

    def __init__(self, cs: int, ct: int, how: str) -> None:
        super().__init__()
        self.how, self.proj = how, conv1x1(cs, ct, 2)

    def forward(self, value: Any, batch: int | None = None) -> Tensor:
        from distilkit.losses.bev import collapse_height

        return self.proj(collapse_height(value, self.how, batch=batch))


def _height(how: str) -> Any:
    def build(cs: int, ct: int, dims: int) -> nn.Module:
        if dims not in (0, 3):
            raise TapError(f"connector height_{how} collapses voxel features over height: it needs (B, C, X, Y, Z) "
                           "features or sparse voxels, not a 2-D map")
        return HeightCollapse(cs, ct, how)
    return build


_height_max, _height_mean = _height("max"), _height("mean")


class Connector(nn.Module):
    """A registered connector (``kind``) from the student's channels to the teacher's, built from one pair of tap
    values; sparse voxels are projected on their features."""

    def __init__(self, kind: str, student: Any, teacher: Any) -> None:
        super().__init__()
        (cs, dims), (ct, _) = _channels(student), _channels(teacher)
        self.proj = CONNECTORS.get(kind)(cs, ct, dims)

    def forward(self, value: Any, batch: int | None = None) -> Any:
        """The projected tap; ``batch``: the batch's size, for a connector that makes a map of sparse voxels."""
        if getattr(self.proj, "whole", False):
            return self.proj(value, batch)
        if isinstance(value, SparseVoxels):
            return value.with_feats(self.proj(value.feats))
        return self.proj(value)
