"""SCPNet's network (Xia et al., CVPR 2023, §3.2, Fig. 3).

* Point featuriser: per-point MLP on 7-d features, max-pooled per voxel (cubic partition).
* Completion sub-network, as the paper describes it: three branches on the voxel volume --
  upper: one Multi-Path Block (MPB); middle: 3x3x3 ConvBlock, two MPBs, 3x3x3 ConvBlock;
  bottom: the identity (residual) -- summed. A ConvBlock is Conv3d (no bias) + ReLU, with no
  BatchNorm, so voxels whose receptive field holds no input stay exactly zero and the
  completed volume stays sparse. An MPB runs 3x3x3, 5x5x5 and 7x7x7 ConvBlocks in parallel
  and fuses them with a 1x1x1 ConvBlock. No down-sampling anywhere.
* Dense -> sparse: the non-zero voxels of the completed volume (the DSKD features).
* Kernel sizes follow the grid: the paper's 3/5/7 MPB paths and 3x3x3 ConvBlocks on 0.2 m
  voxels give the middle branch a receptive radius of 8 voxels = 1.6 m. On coarser grids the
  kernels shrink (:func:`kernels_for_voxel`) so that the radius stays about 1.6 m and the
  completed volume stays as sparse as at full scale, instead of filling the grid.
* Segmentation sub-network: the paper uses Cylinder3D's sparse asymmetric U-Net; here a small
  dense 3-D U-Net (:class:`DenseUNet3d`) stands in, so that CPU runs at coarse grids work. It
  behaves as the sparse network would: voxels outside the completed (active) set are empty
  (a constant logit vector that predicts class 0 and carries no gradient).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from distilkit_adapters._blocks import DenseUNet3d, PointVoxelizer


class ConvBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int) -> None:
        super().__init__(nn.Conv3d(cin, cout, k, padding=k // 2, bias=False), nn.ReLU(inplace=False))


# (MPB path kernels, ConvBlock kernel) by voxel size: middle-branch receptive radius about 1.6 m
_KERNELS = {1: ((3, 5, 7), 3), 2: ((1, 3, 5), 1), 4: ((1, 3), 1), 8: ((1, 3), 1)}
EMPTY_LOGIT = 10.0  # logit of class 0 at inactive voxels (softmax probability of "empty" > 0.9999)


def kernels_for_voxel(voxel_size: float) -> tuple[tuple[int, ...], int]:
    """The paper's kernels at 0.2 m, smaller on coarser grids (see the module docstring)."""
    scale = max(1, round(voxel_size / 0.2))
    for s in sorted(_KERNELS, reverse=True):
        if scale >= s:
            return _KERNELS[s]
    return _KERNELS[1]


def mask_inactive(logits: Tensor, active: Tensor) -> Tensor:
    """Logits where ``active`` (B, X, Y, Z); elsewhere the constant "empty" vector (no gradient)."""
    empty = torch.zeros(logits.shape[1], dtype=logits.dtype, device=logits.device)
    empty[0] = EMPTY_LOGIT
    return torch.where(active.unsqueeze(1), logits, empty.view(1, -1, 1, 1, 1))


class MultiPathBlock(nn.Module):
    """Parallel 3/5/7 ConvBlocks, concatenated, fused by a 1x1x1 ConvBlock (no bias, no BN)."""

    def __init__(self, c: int, kernels: tuple[int, ...] = (3, 5, 7)) -> None:
        super().__init__()
        self.paths = nn.ModuleList(ConvBlock(c, c, k) for k in kernels)
        self.fuse = ConvBlock(c * len(kernels), c, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.fuse(torch.cat([p(x) for p in self.paths], dim=1))


class CompletionSubNetwork(nn.Module):
    """upper = MPB(x); middle = Conv3(MPB(MPB(Conv3(x)))); out = upper + middle + x."""

    def __init__(self, c: int, kernels: tuple[int, ...] = (3, 5, 7), conv_kernel: int = 3) -> None:
        super().__init__()
        self.upper = MultiPathBlock(c, kernels)
        self.middle = nn.Sequential(ConvBlock(c, c, conv_kernel), MultiPathBlock(c, kernels), MultiPathBlock(c, kernels),
                                    ConvBlock(c, c, conv_kernel))

    def forward(self, x: Tensor) -> Tensor:
        return self.upper(x) + self.middle(x) + x


class SCPNet(nn.Module):
    def __init__(self, channels: int, point_mlp: list[int], seg_channels: int, num_classes: int,
                 kernels: tuple[int, ...] = (3, 5, 7), conv_kernel: int = 3) -> None:
        super().__init__()
        self.voxelizer = PointVoxelizer(point_mlp, channels)
        self.completion = CompletionSubNetwork(channels, kernels, conv_kernel)
        self.segmentation = DenseUNet3d(channels, seg_channels, num_classes)
