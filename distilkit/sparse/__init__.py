"""Sparse 3-D convolution with spconv 2.x's API, in pure PyTorch: ``SparseConvTensor``, ``SubMConv3d``,
``SparseConv3d``, ``SparseInverseConv3d`` (weights (out, k0, k1, k2, in), spconv 2.2+'s layout, so state dicts move
between the two unchanged). Neighbour maps by voxel hashing, then gather, a GEMM per kernel offset and a scatter-add;
autograd through features and weights; the same bits in every process on the CPU; no dense grid. The products and
sums run on a backend chosen per call (:mod:`distilkit.sparse.backend`: this PyTorch path, spconv 2.x or
spconv-Triton; ``DISTILKIT_SPARSE``). ``distilkit bench
sparse`` times it at a real scan's occupancy."""

from distilkit.sparse.conv import SparseConv3d, SparseInverseConv3d, SubMConv3d, name_modules, uses_sparse
from distilkit.sparse.tensor import SparseConvTensor

__all__ = ["SparseConv3d", "SparseConvTensor", "SparseInverseConv3d", "SubMConv3d", "name_modules", "uses_sparse"]
