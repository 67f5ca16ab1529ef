"""Tap kinds: the named outputs an adapter's forward returns and objectives consume.

| kind              | value                                                          |
| ----------------- | -------------------------------------------------------------- |
| sparse_features   | :class:`SparseVoxels`: coords (N,4) int64 = batch,x,y,z; feats (N,C) |
| voxel_logits      | (B, K, X, Y, Z) class scores on the SSC grid                    |
| feature_map       | (B, C, H, W) or (B, C, X, Y, Z) dense features                  |
| point_logits      | (M, K) per-point class scores (points of the batch, concatenated) |
| points            | (B, M, 3) points plus a (B, M) bool mask                        |
| scalar            | a 0-d tensor                                                    |
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from torch import Tensor

TAP_KINDS = ("sparse_features", "voxel_logits", "feature_map", "point_logits", "points", "scalar")


@dataclass
class SparseVoxels:
    """Sparse voxel features: ``coords`` (N,4) int64 rows (batch, x, y, z), ``feats`` (N,C).

    ``spatial_shape`` is the (X, Y, Z) grid the coordinates index into.
    """

    coords: Tensor
    feats: Tensor
    spatial_shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        if self.coords.dim() != 2 or self.coords.shape[1] != 4:
            raise ValueError(f"SparseVoxels.coords must be (N, 4) (batch, x, y, z), got {tuple(self.coords.shape)}")
        if self.feats.dim() != 2 or self.feats.shape[0] != self.coords.shape[0]:
            raise ValueError(
                f"SparseVoxels.feats must be (N, C) with N = {self.coords.shape[0]}, got {tuple(self.feats.shape)}"
            )

    def select_batch(self, b: int) -> "SparseVoxels":
        keep = self.coords[:, 0] == b
        return SparseVoxels(self.coords[keep], self.feats[keep], self.spatial_shape)

    def detach(self) -> "SparseVoxels":
        return SparseVoxels(self.coords, self.feats.detach(), self.spatial_shape)


def check_tap(value: Any, kind: str, where: str) -> None:
    """Raise a clear error when a tap's value does not have the declared kind."""
    from distilkit.errors import TapError

    ok = {
        "sparse_features": lambda v: isinstance(v, SparseVoxels),
        "voxel_logits": lambda v: isinstance(v, Tensor) and v.dim() == 5,
        "feature_map": lambda v: isinstance(v, Tensor) and v.dim() in (4, 5),
        "point_logits": lambda v: isinstance(v, Tensor) and v.dim() == 2,
        "points": lambda v: isinstance(v, Tensor) and v.dim() == 3,
        "scalar": lambda v: isinstance(v, Tensor) and v.dim() == 0,
    }[kind](value)
    if not ok:
        shape = tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__
        raise TapError(f"{where}: expected a {kind} tap, got {shape}")


__all__ = ["SparseVoxels", "TAP_KINDS", "check_tap"]
