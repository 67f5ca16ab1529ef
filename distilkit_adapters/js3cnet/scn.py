"""SparseConvNet's layers (facebookresearch/SparseConvNet, as vendored in JS3C-Net's ``lib/``) on
:mod:`distilkit.sparse`, with its parameter names and layouts, so that a state dict it saved loads unchanged:

* ``SubmanifoldConvolution``, ``Convolution`` (size 2, stride 2), ``Deconvolution``: ``weight`` (filter volume,
  groups = 1, in, out), no bias. The filter index runs in C order over d = input - output (+ the padding, size // 2,
  for a submanifold one; ``Metadata/SubmanifoldConvolutionRules.h``, ``RectangularRegions.h``: the last axis
  fastest) and each slice is applied as ``features @ W`` — spconv 2.x's (K, in, out) matrices in the same order, so
  the weight is used as it is. A strided convolution reads inputs o s .. o s + size - 1 of output o, its
  deconvolution writes back onto that convolution's input sites.
* ``NetworkInNetwork``: ``weight`` (in, out), ``features @ W``.
* ``BatchNormReLU`` / ``BatchNormLeakyReLU``: ``weight``, ``bias``, ``running_mean``, ``running_var`` and no
  ``num_batches_tracked``; eps 1e-4; momentum 0.9 on the running statistics (torch's 0.1 on the new batch), the
  batch normalised by its biased variance and the running variance updated with the unbiased one
  (``CPU/BatchNormalization.cpp``), then LeakyReLU of ``leakiness`` (``scn.UNet``'s default 0: a ReLU).
* ``Sequential``, ``ConcatTable``, ``AddTable``, ``JoinTable``, ``Identity``, ``InputLayer``, ``OutputLayer``:
  containers without parameters that hold their children under ``0``, ``1``, ... as scn's do (the network maps
  points to voxels and back itself, so the two IO layers only keep their places in the names).

:func:`unet` is ``scn.UNet(3, reps, nPlanes, residual_blocks, downsample=[2, 2])``.
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d


def _scn_weight(volume: int, nin: int, nout: int) -> nn.Parameter:
    """scn's (filter volume, 1, in, out) weight with its initialisation, normal(0, sqrt(2 / (in volume)))."""
    return nn.Parameter(torch.empty(volume, 1, nin, nout).normal_(0, (2.0 / nin / volume) ** 0.5))


class SubmanifoldConvolution(SubMConv3d):
    """``scn.SubmanifoldConvolution(3, nIn, nOut, 3, False)``; the level's sites share one neighbour map."""

    def __init__(self, nin: int, nout: int, level: int, filter_size: int = 3) -> None:
        super().__init__(nin, nout, filter_size, padding=filter_size // 2, bias=False, indice_key=f"scn_subm{level}")
        self.weight = _scn_weight(self.volume, nin, nout)

    def kernel_matrices(self) -> torch.Tensor:
        return self.weight[:, 0]


class Convolution(SparseConv3d):
    """``scn.Convolution(3, nIn, nOut, 2, 2, False)``: level ``level`` to the next."""

    def __init__(self, nin: int, nout: int, level: int) -> None:
        super().__init__(nin, nout, 2, stride=2, bias=False, indice_key=f"scn_down{level}")
        self.weight = _scn_weight(8, nin, nout)

    def kernel_matrices(self) -> torch.Tensor:
        return self.weight[:, 0]


class Deconvolution(SparseInverseConv3d):
    """``scn.Deconvolution(3, nIn, nOut, 2, 2, False)``: back onto the sites of level ``level``'s convolution."""

    def __init__(self, nin: int, nout: int, level: int) -> None:
        super().__init__(nin, nout, 2, indice_key=f"scn_down{level}", bias=False)
        self.weight = _scn_weight(8, nin, nout)

    def kernel_matrices(self) -> torch.Tensor:
        return self.weight[:, 0]


class NetworkInNetwork(nn.Module):
    """``scn.NetworkInNetwork(nIn, nOut, False)``: a per-site linear map, weight (in, out)."""

    def __init__(self, nin: int, nout: int) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.empty(nin, nout).normal_(0, (2.0 / nin) ** 0.5))

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return x.replace_feature(x.features @ self.weight)


class BatchNormReLU(nn.Module):
    """``scn.BatchNormReLU`` / ``BatchNormLeakyReLU(n, leakiness=0)``: scn's batch norm, then LeakyReLU."""

    def __init__(self, planes: int, leakiness: float = 0.0, eps: float = 1e-4, momentum: float = 0.9) -> None:
        super().__init__()
        self.eps, self.momentum, self.leakiness = eps, momentum, leakiness
        self.weight = nn.Parameter(torch.ones(planes))
        self.bias = nn.Parameter(torch.zeros(planes))
        self.register_buffer("running_mean", torch.zeros(planes))
        self.register_buffer("running_var", torch.ones(planes))

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        out = F.batch_norm(x.features, self.running_mean, self.running_var, self.weight, self.bias, self.training,
                           1.0 - self.momentum, self.eps)
        return x.replace_feature(F.leaky_relu(out, self.leakiness) if self.leakiness else F.relu(out))

    def extra_repr(self) -> str:
        return f"{len(self.weight)}, eps={self.eps}, momentum={self.momentum}, leakiness={self.leakiness}"


class Sequential(nn.Sequential):
    """``scn.Sequential``: children ``0``, ``1``, ... applied in turn (to a tensor or to a table of them)."""

    def add(self, module: nn.Module) -> "Sequential":
        self.add_module(str(len(self)), module)
        return self


class ConcatTable(nn.Module):
    """``scn.ConcatTable``: every child on the same input, the outputs as a list."""

    def add(self, module: nn.Module) -> "ConcatTable":
        self.add_module(str(len(self._modules)), module)
        return self

    def forward(self, x: SparseConvTensor) -> list[SparseConvTensor]:
        return [child(x) for child in self._modules.values()]


class AddTable(nn.Module):
    """``scn.AddTable``: the sum of a table's features (on the first one's sites)."""

    def forward(self, xs: list[SparseConvTensor]) -> SparseConvTensor:
        total = xs[0].features
        for x in xs[1:]:
            total = total + x.features
        return xs[0].replace_feature(total)


class JoinTable(nn.Module):
    """``scn.JoinTable``: a table's features concatenated in order (on the first one's sites)."""

    def forward(self, xs: list[SparseConvTensor]) -> SparseConvTensor:
        return xs[0].replace_feature(torch.cat([x.features for x in xs], 1))


class Identity(nn.Module):
    def forward(self, x: Any) -> Any:
        return x


class InputLayer(Identity):
    """``scn.InputLayer(3, size, mode=4)``'s place: the caller has averaged each voxel's points (mode 4)."""


class OutputLayer(Identity):
    """``scn.OutputLayer(3)``'s place: the caller gives every point its voxel's features."""


def _block(m: Sequential, a: int, b: int, residual: bool, level: int) -> None:
    """``scn.UNet``'s block: pre-activated, residual (an identity or a NetworkInNetwork shortcut) or VGG style."""
    body = Sequential().add(BatchNormReLU(a)).add(SubmanifoldConvolution(a, b, level))
    if residual:
        body.add(BatchNormReLU(b)).add(SubmanifoldConvolution(b, b, level))
        m.add(ConcatTable().add(Identity() if a == b else NetworkInNetwork(a, b)).add(body)).add(AddTable())
    else:
        m.add(body)


def unet(reps: int, planes: list[int], residual: bool = True, level: int = 0) -> Sequential:
    """``scn.UNet(3, reps, planes, residual_blocks=residual)``: ``reps`` blocks, then (but at the last level) a
    skip beside [BN-ReLU, 2^3 stride-2 convolution, the next levels, BN-ReLU, deconvolution], their features joined
    and ``reps`` blocks again (the first from twice the width)."""
    m = Sequential()
    for _ in range(reps):
        _block(m, planes[0], planes[0], residual, level)
    if len(planes) > 1:
        down = (Sequential().add(BatchNormReLU(planes[0])).add(Convolution(planes[0], planes[1], level))
                .add(unet(reps, planes[1:], residual, level + 1)).add(BatchNormReLU(planes[1]))
                .add(Deconvolution(planes[1], planes[0], level)))
        m.add(ConcatTable().add(Identity()).add(down)).add(JoinTable())
        for i in range(reps):
            _block(m, planes[0] * (2 if i == 0 else 1), planes[0], residual, level)
    return m


__all__ = ["AddTable", "BatchNormReLU", "ConcatTable", "Convolution", "Deconvolution", "Identity", "InputLayer",
           "JoinTable", "NetworkInNetwork", "OutputLayer", "Sequential", "SubmanifoldConvolution", "unet"]
