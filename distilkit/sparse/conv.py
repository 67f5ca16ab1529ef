"""Sparse 3-D convolution modules with spconv 2.x's names, arguments and weight layout.

``weight`` is (out, k0, k1, k2, in) — spconv 2.2+'s layout (2.1 mostly, 2.0 had (k0, k1, k2, out, in) and 1.x
(k0, k1, k2, in, out): :func:`distilkit.sparse.convert.to_spconv2` converts those) — and ``bias`` (out,), so a state
dict moves between spconv and distilkit unchanged. ``indice_key`` names a neighbour map kept on the tensor: a
submanifold convolution with the key of an earlier one reuses its map, and ``SparseInverseConv3d(indice_key=K)``
inverts the strided ``SparseConv3d(indice_key=K)`` that produced its input's ancestors, back onto that
convolution's input sites (spconv's decoder pattern).

Pure PyTorch (:mod:`distilkit.sparse.rulebook`, :mod:`distilkit.sparse.function`): no dense grid is allocated,
autograd flows through features and weights, and the CPU results are the same bits in any process.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import Tensor, nn

from distilkit.sparse.function import rulebook_conv
from distilkit.sparse.rulebook import Rulebook, strided, submanifold, triple
from distilkit.sparse.tensor import SparseConvTensor


class _SparseConvolution(nn.Module):
    """What the three kinds share: the weight (out, k0, k1, k2, in), the bias, spconv's initialisation."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int], stride: int | Sequence[int],
                 padding: int | Sequence[int], dilation: int | Sequence[int], bias: bool,
                 indice_key: str | None) -> None:
        super().__init__()
        self.in_channels, self.out_channels = int(in_channels), int(out_channels)
        self.kernel_size = triple(kernel_size, "kernel_size")
        self.stride, self.padding = triple(stride, "stride"), triple(padding, "padding")
        self.dilation = triple(dilation, "dilation")
        self.indice_key = indice_key
        self.weight = nn.Parameter(torch.empty(self.out_channels, *self.kernel_size, self.in_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Kaiming-uniform weights (a = sqrt(5)) and a uniform bias over +-1/sqrt(fan_in), as nn.Conv3d and spconv."""
        fan_in = self.in_channels * math.prod(self.kernel_size)
        bound = math.sqrt(6.0 / ((1 + 5) * fan_in))  # kaiming_uniform_ with a = sqrt(5), gain sqrt(2 / (1 + a^2))
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            b = 1 / math.sqrt(fan_in) if fan_in > 0 else 0.0
            nn.init.uniform_(self.bias, -b, b)

    def kernel_matrices(self) -> Tensor:
        """The weight as (K, in, out): one matrix per kernel index in C order."""
        return self.weight.permute(1, 2, 3, 4, 0).reshape(-1, self.in_channels, self.out_channels)

    def _run(self, x: SparseConvTensor, book: Rulebook, rows_out: int) -> Tensor:
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"{type(self).__name__}: {x.features.shape[1]} input channels, expected "
                             f"{self.in_channels}")
        out = rulebook_conv(x.features, self.kernel_matrices(), book, rows_out)
        return out + self.bias if self.bias is not None else out

    def extra_repr(self) -> str:
        key = f", indice_key={self.indice_key!r}" if self.indice_key else ""
        return (f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
                f"padding={self.padding}, dilation={self.dilation}, bias={self.bias is not None}{key}")


class SubMConv3d(_SparseConvolution):
    """Submanifold convolution: outputs at the input's sites only (odd kernels, e.g. Cylinder3D's 1x3x3, 3x1x3,
    3x3x1 and 3x3x3)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int] = 3, stride: int = 1,
                 padding: int | Sequence[int] = 0, dilation: int | Sequence[int] = 1, groups: int = 1,
                 bias: bool = True, indice_key: str | None = None, **_: object) -> None:
        if groups != 1:
            raise ValueError("SubMConv3d: groups other than 1 are not supported")
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key)

    def rulebook(self, x: SparseConvTensor) -> Rulebook:
        kept = x.indice_dict.get(self.indice_key) if self.indice_key else None
        if isinstance(kept, Rulebook) and kept.in_indices is kept.out_indices and kept.in_indices is x.indices \
                and kept.kernel == self.kernel_size and kept.dilation == self.dilation:
            return kept
        book = submanifold(x.indices, x.spatial_shape, self.kernel_size, self.dilation)
        if self.indice_key:
            x.indice_dict[self.indice_key] = book
        return book

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        book = self.rulebook(x)
        out = self._run(x, book, x.features.shape[0])
        return SparseConvTensor(out, x.indices, x.spatial_shape, x.batch_size, x.indice_dict)


class SparseConv3d(_SparseConvolution):
    """A regular sparse convolution (strided, padded, dilated): active outputs wherever an active input reaches."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int] = 3,
                 stride: int | Sequence[int] = 1, padding: int | Sequence[int] = 0, dilation: int | Sequence[int] = 1,
                 groups: int = 1, bias: bool = True, indice_key: str | None = None, **_: object) -> None:
        if groups != 1:
            raise ValueError("SparseConv3d: groups other than 1 are not supported")
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        book = strided(x.indices, x.spatial_shape, self.kernel_size, self.stride, self.padding, self.dilation)
        if self.indice_key:
            x.indice_dict[self.indice_key] = book
        out = self._run(x, book, book.out_indices.shape[0])
        return SparseConvTensor(out, book.out_indices, book.out_shape, x.batch_size, x.indice_dict)


class SparseInverseConv3d(_SparseConvolution):
    """The transpose of the ``SparseConv3d`` with the same ``indice_key``: back onto that convolution's input
    sites and grid (conv_transpose3d there)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int], indice_key: str,
                 bias: bool = True, **_: object) -> None:
        super().__init__(in_channels, out_channels, kernel_size, 1, 0, 1, bias, indice_key)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        book = x.indice_dict.get(self.indice_key) if self.indice_key else None
        if not isinstance(book, Rulebook) or book.in_indices is book.out_indices:
            raise KeyError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): no strided SparseConv3d with that "
                           f"key ran on this tensor's ancestors (keys: {', '.join(map(str, x.indice_dict)) or 'none'})")
        if book.kernel != self.kernel_size:
            raise ValueError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): kernel {self.kernel_size}, but "
                             f"the convolution it inverts had {book.kernel}")
        if x.features.shape[0] != book.out_indices.shape[0]:
            raise ValueError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): {x.features.shape[0]} input "
                             f"voxels, but the convolution it inverts produced {book.out_indices.shape[0]}")
        back = book.inverse()
        out = self._run(x, back, back.out_indices.shape[0])
        return SparseConvTensor(out, back.out_indices, back.out_shape, x.batch_size, x.indice_dict)


__all__ = ["SparseConv3d", "SparseInverseConv3d", "SubMConv3d"]
