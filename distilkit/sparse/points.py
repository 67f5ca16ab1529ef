"""Points into sparse voxels and back, as MinkowskiEngine's ``TensorField`` does it for LiDiff: coordinates
``round(p / resolution)``, each voxel's features the unweighted average of its points' (``UNWEIGHTED_AVERAGE``), and
``slice`` giving every point its voxel's features. The grid is shifted so that indices start at 0 (a sparse grid has
no negative indices); the shift is a multiple of ``align`` voxels (the network's total stride), so strided
convolutions floor exactly as they would on the unshifted coordinates."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from distilkit.sparse.tensor import SparseConvTensor


@dataclass
class Voxelized:
    """A batch of point clouds as sparse voxels: the tensor, each point's voxel row (for :meth:`slice`) and the
    shift from grid indices to ``round(p / resolution)`` coordinates (``coords = indices + shift``)."""

    tensor: SparseConvTensor
    point_rows: Tensor  # (P,) int64, the voxel row of every point (batch-major order of the input)
    shift: Tensor  # (3,) int64
    resolution: float

    def coordinates(self, indices: Tensor, stride: int = 1) -> Tensor:
        """(N, 3) float coordinates in voxels of ``resolution`` (as MinkowskiEngine keeps them at any tensor stride)
        of (N, 4) indices on a grid ``stride`` times coarser."""
        return (indices[:, 1:].long() * stride + self.shift).to(torch.float32)

    def slice(self, features: Tensor) -> Tensor:
        """(P, C): every point's voxel's row of ``features`` (N, C) at the input's resolution."""
        return features.index_select(0, self.point_rows)


def voxelize(points: Tensor, resolution: float, align: int = 1, features: Tensor | None = None) -> Voxelized:
    """(B, M, 3) points (metres) -> sparse voxels of ``round(p / resolution)``, their features the mean of the
    points' ``features`` (default: the points themselves, LiDiff's), batch-major rows sorted by (batch, x, y, z)."""
    b, m, _ = points.shape
    feats = points if features is None else features
    batch = torch.arange(b, device=points.device).repeat_interleave(m)
    return voxelize_flat(points.reshape(b * m, 3), batch, b, resolution, align, feats.reshape(b * m, -1),
                         rounding="round")


def voxelize_flat(points: Tensor, batch: Tensor, batch_size: int, resolution: float, align: int = 1,
                  features: Tensor | None = None, rounding: str = "round") -> Voxelized:
    """:func:`voxelize` for (P, 3) points with their (P,) batch indices; ``rounding`` ``round`` (MinkowskiEngine's
    ``round(p / r)``) or ``floor`` (a voxel grid's cells ``[i r, (i + 1) r)``)."""
    flat = points if features is None else features
    scaled = points.detach() / resolution
    coords = (torch.round(scaled) if rounding == "round" else torch.floor(scaled)).long()
    low = coords.min(dim=0).values if coords.numel() else torch.zeros(3, dtype=torch.long, device=points.device)
    shift = torch.div(low, align, rounding_mode="floor") * align
    grid = coords - shift
    size = (grid.max(dim=0).values + 1) if grid.numel() else torch.ones(3, dtype=torch.long, device=points.device)
    size = ((size + align - 1) // align) * align  # a whole number of the coarsest voxels
    key = ((batch.long() * size[0] + grid[:, 0]) * size[1] + grid[:, 1]) * size[2] + grid[:, 2]
    keys, rows = torch.unique(key, return_inverse=True)
    summed = flat.new_zeros((len(keys), flat.shape[1])).index_add_(0, rows, flat)
    counts = torch.bincount(rows, minlength=len(keys)).clamp_min(1).to(flat.dtype)
    indices = torch.empty((len(keys), 4), dtype=torch.long, device=points.device)
    indices[:, 3] = keys % size[2]
    r = keys // size[2]
    indices[:, 2] = r % size[1]
    r = r // size[1]
    indices[:, 1] = r % size[0]
    indices[:, 0] = r // size[0]
    tensor = SparseConvTensor(summed / counts[:, None], indices.int(), [int(s) for s in size], batch_size)
    return Voxelized(tensor, rows, shift, resolution)


__all__ = ["Voxelized", "voxelize", "voxelize_flat"]
