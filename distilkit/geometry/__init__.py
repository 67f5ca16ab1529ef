"""Shared numerics: voxel hashing, sparse alignment, voxelisation, nearest neighbours (imported on first use;
:mod:`distilkit.geometry.grids` is plain Python)."""

from typing import Any

_LAZY = {"VoxelGrid": "voxel", "align_across_grids": "voxel", "align_sparse": "voxel", "grid_factors": "grids",
         "dense_to_sparse": "voxel", "voxel_hash": "voxel", "knn": "knn"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"distilkit.geometry.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'distilkit.geometry' has no attribute {name!r}")


__all__ = ["VoxelGrid", "align_across_grids", "align_sparse", "grid_factors", "dense_to_sparse", "voxel_hash", "knn"]
