"""Shared numerics: voxel hashing, sparse alignment, voxelisation, nearest neighbours."""

from distilkit.geometry.voxel import (
    VoxelGrid,
    align_sparse,
    dense_to_sparse,
    voxel_hash,
)
from distilkit.geometry.knn import knn

__all__ = ["VoxelGrid", "align_sparse", "dense_to_sparse", "voxel_hash", "knn"]
