"""Sparse 3-D convolution with spconv 2.x's API, in pure PyTorch: ``SparseConvTensor``, ``SubMConv3d``,
``SparseConv3d``, ``SparseInverseConv3d`` (weights (out, k0, k1, k2, in), spconv 2.2+'s layout, so state dicts move
between the two unchanged). Neighbour maps by voxel hashing, then gather, a GEMM per kernel offset and a scatter-add;
autograd through features and weights; the same bits in every process on the CPU; no dense grid. The products and
sums run on a backend chosen per call (:mod:`distilkit.sparse.backend`: this PyTorch path, spconv 2.x or
spconv-Triton; ``DISTILKIT_SPARSE``). ``distilkit bench
sparse`` times it at a real scan's occupancy."""

from typing import Any

_LAZY = {"SparseConv3d": "conv", "SparseInverseConv3d": "conv", "SubMConv3d": "conv", "name_modules": "conv",
         "uses_sparse": "conv", "SparseConvTensor": "tensor"}


def __getattr__(name: str) -> Any:
    """The layers, imported on first use (``distilkit.sparse.choice`` is read without torch)."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"distilkit.sparse.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'distilkit.sparse' has no attribute {name!r}")


__all__ = ["SparseConv3d", "SparseConvTensor", "SparseInverseConv3d", "SubMConv3d", "name_modules", "uses_sparse"]
