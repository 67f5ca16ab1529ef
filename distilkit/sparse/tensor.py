"""``SparseConvTensor``: active voxels of a batch of 3-D grids, as spconv 2.x holds them.

``features`` (N, C), ``indices`` int32 (N, 4) = (batch, x, y, z), ``spatial_shape`` (X, Y, Z) and ``batch_size``;
``indice_dict`` keeps the neighbour maps (rulebooks) of the convolutions that ran on it by their ``indice_key``, so a
later submanifold convolution with the same key, or the inverse of a strided one, reuses them instead of hashing
again (spconv's contract: a tensor and the ones derived from it by ``replace_feature`` share the dictionary).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


class SparseConvTensor:
    """A batch of sparse 3-D grids (spconv 2.x's API)."""

    def __init__(self, features: Tensor, indices: Tensor, spatial_shape: Any, batch_size: int,
                 indice_dict: dict[str, Any] | None = None) -> None:
        shape = tuple(int(s) for s in spatial_shape)
        if len(shape) != 3:
            raise ValueError(f"SparseConvTensor: spatial_shape must have 3 sizes (X, Y, Z), got {shape}")
        if features.dim() != 2:
            raise ValueError(f"SparseConvTensor: features must be (N, C), got {tuple(features.shape)}")
        if indices.dim() != 2 or indices.shape[1] != 4 or indices.shape[0] != features.shape[0]:
            raise ValueError(f"SparseConvTensor: indices must be (N, 4) = (batch, x, y, z) for N = "
                             f"{features.shape[0]} features, got {tuple(indices.shape)}")
        if indices.dtype not in (torch.int32, torch.int64):
            raise ValueError(f"SparseConvTensor: indices must be integers (int32), got {indices.dtype}")
        self.features = features
        self.indices = indices
        self.spatial_shape = list(shape)
        self.batch_size = int(batch_size)
        self.indice_dict: dict[str, Any] = {} if indice_dict is None else indice_dict

    def replace_feature(self, features: Tensor) -> "SparseConvTensor":
        """The same voxels (and neighbour maps) with other features, e.g. after a BatchNorm or an activation."""
        if features.shape[0] != self.features.shape[0]:
            raise ValueError(f"replace_feature: {features.shape[0]} rows for {self.features.shape[0]} voxels")
        return SparseConvTensor(features, self.indices, self.spatial_shape, self.batch_size, self.indice_dict)

    @property
    def shape(self) -> list[int]:
        """(B, X, Y, Z, C) of the dense grid."""
        return [self.batch_size, *self.spatial_shape, int(self.features.shape[1])]

    def dense(self, channels_first: bool = True) -> Tensor:
        """The dense (B, C, X, Y, Z) grid (``channels_first=False``: (B, X, Y, Z, C)); zero where nothing is
        active. Memory: the whole grid — for checks and small grids."""
        c = self.features.shape[1]
        out = self.features.new_zeros((self.batch_size, *self.spatial_shape, c))
        idx = self.indices.long()
        out[idx[:, 0], idx[:, 1], idx[:, 2], idx[:, 3]] = self.features
        return out.permute(0, 4, 1, 2, 3).contiguous() if channels_first else out

    @classmethod
    def from_dense(cls, dense: Tensor) -> "SparseConvTensor":
        """The active voxels (any feature non-zero) of a dense (B, C, X, Y, Z) grid."""
        if dense.dim() != 5:
            raise ValueError(f"from_dense expects (B, C, X, Y, Z), got {tuple(dense.shape)}")
        channels_last = dense.permute(0, 2, 3, 4, 1)
        active = channels_last.abs().sum(dim=-1) > 0
        indices = active.nonzero().int()
        return cls(channels_last[active], indices, dense.shape[2:], dense.shape[0])

    def __repr__(self) -> str:
        return (f"SparseConvTensor({self.features.shape[0]} voxels x {self.features.shape[1]} channels, "
                f"spatial_shape={self.spatial_shape}, batch_size={self.batch_size})")


__all__ = ["SparseConvTensor"]
