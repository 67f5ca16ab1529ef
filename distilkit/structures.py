"""The data structures every part of distilkit passes around, in one place and importing nothing of distilkit:
:class:`VoxelGrid` (a grid's geometry), :class:`SparseVoxels` (sparse voxel features on a grid) and
:class:`PointCloud` (a batch of point clouds of different sizes)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # torch is imported where a method computes, so describing a grid needs no torch
    import torch
    from torch import Tensor


@dataclass(frozen=True)
class VoxelGrid:
    """An axis-aligned grid: x forward, y left, z up; ``origin`` is the min corner of voxel (0,0,0).

    SemanticKITTI SSC: origin (0, -25.6, -2), 256 x 256 x 32 voxels of 0.2 m. ``scale`` s gives
    the same volume with s-times coarser voxels (s = 4: 64 x 64 x 8 at 0.8 m).
    """

    origin: tuple[float, float, float] = (0.0, -25.6, -2.0)
    shape: tuple[int, int, int] = (256, 256, 32)
    voxel_size: float = 0.2

    @classmethod
    def semantickitti(cls, scale: int = 1) -> "VoxelGrid":
        if scale < 1 or 256 % scale or 32 % scale:
            raise ValueError(f"grid scale must divide 256 and 32 (1, 2, 4, 8, 16, 32), got {scale}")
        return cls((0.0, -25.6, -2.0), (256 // scale, 256 // scale, 32 // scale), 0.2 * scale)

    def index(self, xyz: Tensor) -> tuple[Tensor, Tensor]:
        """Voxel indices (M,3) int64 of points (M,3) and a bool mask of points inside the grid."""
        import torch

        origin = torch.tensor(self.origin, dtype=xyz.dtype, device=xyz.device)
        idx = torch.floor((xyz - origin) / self.voxel_size).long()
        shape = torch.tensor(self.shape, device=xyz.device)
        inside = ((idx >= 0) & (idx < shape)).all(dim=1)
        return idx, inside

    def centers(self, idx: Tensor) -> Tensor:
        """Voxel centres (M,3) of integer indices (M,3)."""
        import torch

        origin = torch.tensor(self.origin, dtype=torch.float32, device=idx.device)
        return origin + (idx.float() + 0.5) * self.voxel_size

    def coarsen(self, factor: int) -> "VoxelGrid":
        return VoxelGrid(self.origin, tuple(s // factor for s in self.shape), self.voxel_size * factor)  # type: ignore[arg-type]


@dataclass
class SparseVoxels:
    """Sparse voxel features: ``coords`` (N,4) int64 rows (batch, x, y, z), ``feats`` (N,C).

    ``spatial_shape`` is the (X, Y, Z) grid the coordinates index into; ``grid``, where the model knows
    it, is that grid's geometry (origin, voxel size), which cross-grid alignment then checks.
    """

    coords: Tensor
    feats: Tensor
    spatial_shape: tuple[int, int, int]
    grid: VoxelGrid | None = None

    def __post_init__(self) -> None:
        if self.coords.dim() != 2 or self.coords.shape[1] != 4:
            raise ValueError(f"SparseVoxels.coords must be (N, 4) (batch, x, y, z), got {tuple(self.coords.shape)}")
        if self.feats.dim() != 2 or self.feats.shape[0] != self.coords.shape[0]:
            raise ValueError(
                f"SparseVoxels.feats must be (N, C) with N = {self.coords.shape[0]}, got {tuple(self.feats.shape)}"
            )
        if self.grid is not None and tuple(self.grid.shape) != tuple(self.spatial_shape):
            raise ValueError(f"SparseVoxels.grid has shape {tuple(self.grid.shape)} but spatial_shape is "
                             f"{tuple(self.spatial_shape)}")

    def select_batch(self, b: int) -> "SparseVoxels":
        keep = self.coords[:, 0] == b
        return SparseVoxels(self.coords[keep], self.feats[keep], self.spatial_shape, self.grid)

    def with_feats(self, feats: Tensor) -> "SparseVoxels":
        """The same voxels with other features (N, C')."""
        return SparseVoxels(self.coords, feats, self.spatial_shape, self.grid)

    def detach(self) -> "SparseVoxels":
        return self.with_feats(self.feats.detach())

    def to(self, device: torch.device | str) -> "SparseVoxels":
        """The same voxels with coordinates and features on ``device``."""
        return SparseVoxels(self.coords.to(device), self.feats.to(device), self.spatial_shape, self.grid)


@dataclass
class PointCloud:
    """A batch of point clouds of different sizes: ``points`` (B, M, D) padded, ``lengths`` (B,) int64
    (cloud b is ``points[b, :lengths[b]]``; D = 3 for xyz, more for features)."""

    points: Tensor
    lengths: Tensor

    def __post_init__(self) -> None:
        import torch

        if self.points.dim() != 3:
            raise ValueError(f"PointCloud.points must be (B, M, D), got {tuple(self.points.shape)}")
        if self.lengths.shape != self.points.shape[:1] or self.lengths.dtype != torch.int64:
            raise ValueError(f"PointCloud.lengths must be ({self.points.shape[0]},) int64, got "
                             f"{tuple(self.lengths.shape)} {self.lengths.dtype}")
        if len(self.lengths) and (int(self.lengths.min()) < 0 or int(self.lengths.max()) > self.points.shape[1]):
            raise ValueError(f"PointCloud.lengths must lie in 0..{self.points.shape[1]}, got {self.lengths.tolist()}")

    def cloud(self, b: int) -> Tensor:
        """(lengths[b], D) points of cloud ``b``."""
        return self.points[b, : int(self.lengths[b])]

    @classmethod
    def from_list(cls, clouds: list[Tensor]) -> "PointCloud":
        """Pad a list of (M_b, D) clouds."""
        import torch

        m = max((len(c) for c in clouds), default=0)
        d = clouds[0].shape[1] if clouds else 3
        points = clouds[0].new_zeros((len(clouds), m, d)) if clouds else torch.zeros(0, 0, 3)
        for b, c in enumerate(clouds):
            points[b, : len(c)] = c
        return cls(points, torch.tensor([len(c) for c in clouds], dtype=torch.int64, device=points.device))

    def detach(self) -> "PointCloud":
        return PointCloud(self.points.detach(), self.lengths)


__all__ = ["PointCloud", "SparseVoxels", "VoxelGrid"]
