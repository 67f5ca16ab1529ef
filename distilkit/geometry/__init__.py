"""Shared numerics: voxel hashing, sparse alignment, voxelisation, nearest neighbours."""

from distilkit.geometry.voxel import (
    VoxelGrid,
    align_across_grids,
    align_sparse,
    grid_factors,
    dense_to_sparse,
    voxel_hash,
)
from distilkit.geometry.knn import knn

__all__ = ["VoxelGrid", "align_across_grids", "align_sparse", "grid_factors", "dense_to_sparse", "voxel_hash", "knn"]
