"""The Dean-Labeler at the paper's size (Wang et al., Scribble2Scene, IJCAI 2024, §4.2 and §5.1 "Implementation
Details": "we adopt Cylinder3D as the SCN backbone"): Cylinder3D's asymmetric sparse U-Net — the SCPNet adapter's
(:class:`distilkit_adapters.scpnet.cylinder.Asymm3dSpconv` without SCPNet's completion sub-network: ``downCntx``,
``resBlock2..5``, ``upBlock0..3``, ``ReconNet``, ``logits``; 32 channels, Cylinder3D's ``init_size``) — run on the
complete geometry's occupied voxels. Its submanifold convolutions, strided pooling and inverse convolutions keep the
active set, so the output lives on exactly the input's voxels: the network cannot change the geometry (§4.2, "the
SCN does not change the geometric structure of the input"; IoU 100 %, Table 3).

There is no point featuriser: Cylinder3D's ``cylinder_3d_generator`` reads LiDAR points, the Dean reads voxels. Each
occupied voxel carries the features :func:`voxel_inputs` gives (``features``), which ``downCntx`` reads directly, so
the network's parameters are Cylinder3D's U-Net's at that input width.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from distilkit.sparse import SparseConvTensor, name_modules
from distilkit.sparse.conv import Semantics
from distilkit_adapters.dean.card import Features
from distilkit_adapters.scpnet.cylinder import Asymm3dSpconv

AXES: dict[str, tuple[int, ...]] = {"occupancy": (), "height": (2,), "position": (0, 1, 2)}  # scaled coordinates
WIDTHS: dict[str, int] = {name: 1 + len(axes) for name, axes in AXES.items()}  # a 1, then the coordinates
INIT_SIZE = 32  # Cylinder3D's init_size (config/semantickitti.yaml), as the SCPNet adapter's paper network


def _axis(n: int, like: Tensor) -> Tensor:
    """Voxel index -> [-1, 1] along an axis of ``n`` voxels (the tiny stand-in's height coordinate)."""
    return torch.linspace(-1.0, 1.0, n, device=like.device)


def _axes(features: str) -> tuple[int, ...]:
    if features not in AXES:
        raise ValueError(f"features must be one of {sorted(AXES)}, got {features!r}")
    return AXES[features]


def voxel_inputs(indices: Tensor, shape: tuple[int, int, int], features: Features) -> Tensor:
    """(N, width) input features of the occupied voxels ``indices`` (N, 4) = (batch, x, y, z) on a grid ``shape``:
    ``occupancy`` a 1 (the binary geometry G as §4.2 states it), ``height`` a 1 and z scaled to [-1, 1] (the tiny
    stand-in's input), ``position`` a 1 and x, y, z scaled to [-1, 1] (the positions Cylinder3D's point features
    carry)."""
    cols = [torch.ones(len(indices), device=indices.device)]
    cols += [_axis(shape[a], indices)[indices[:, 1 + a].long()] for a in _axes(features)]
    return torch.stack(cols, 1)


def dense_inputs(occupied: Tensor, features: Features) -> Tensor:
    """(B, width, X, Y, Z): :func:`voxel_inputs` at the occupied voxels of ``occupied`` (B, X, Y, Z), 0 elsewhere."""
    occ = occupied.float()
    cols = [occ]
    for a in _axes(features):
        view = [1, 1, 1]
        view[a] = -1
        cols.append(_axis(occupied.shape[1 + a], occupied).view(view).expand(occupied.shape[1:]) * occ)
    return torch.stack(cols, 1)


class DeanCylinder(nn.Module):
    """Cylinder3D's asymmetric sparse U-Net over the occupied voxels (module names as Cylinder3D's release:
    ``cylinder_3d_spconv_seg.*``)."""

    def __init__(self, num_classes: int, features: Features = "height", semantics: Semantics = "spconv1") -> None:
        super().__init__()
        self.features = features
        self.cylinder_3d_spconv_seg = Asymm3dSpconv(WIDTHS[features], INIT_SIZE, num_classes, semantics,
                                                    completion=False)
        name_modules(self)

    def forward(self, occupied: Tensor) -> tuple[Tensor, Tensor]:
        """``occupied`` (B, X, Y, Z) bool -> (features (B, 4 x 32, X, Y, Z): the U-Net's last features, which the
        logit convolution reads; logits (B, K, X, Y, Z)), both 0 outside the occupied voxels. Memory: the features'
        dense grid is 1 GiB per sample at 256 x 256 x 32 (float32)."""
        shape = tuple(occupied.shape[1:])
        indices = occupied.nonzero()
        x = SparseConvTensor(voxel_inputs(indices, shape, self.features), indices.int(), shape, occupied.shape[0])
        seg = self.cylinder_3d_spconv_seg
        last = seg.segment_features(x)
        return last.dense(), seg.logits(last).dense()


__all__ = ["DeanCylinder", "Features", "WIDTHS", "dense_inputs", "voxel_inputs"]
