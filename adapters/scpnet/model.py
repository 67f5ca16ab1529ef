"""SCPNet's network (Xia et al., CVPR 2023, §3.2, Fig. 3).

* Point featuriser: per-point MLP on 7-d features, max-pooled per voxel (cubic partition).
* Completion sub-network, as the paper describes it: three branches on the voxel volume --
  upper: one Multi-Path Block (MPB); middle: 3x3x3 ConvBlock, two MPBs, 3x3x3 ConvBlock;
  bottom: the identity (residual) -- summed. A ConvBlock is Conv3d (no bias) + ReLU, with no
  BatchNorm, so voxels whose receptive field holds no input stay exactly zero and the
  completed volume stays sparse. An MPB runs 3x3x3, 5x5x5 and 7x7x7 ConvBlocks in parallel
  and fuses them with a 1x1x1 ConvBlock. No down-sampling anywhere.
* Dense -> sparse: the non-zero voxels of the completed volume (the DSKD features).
* Segmentation sub-network: the paper uses Cylinder3D's sparse asymmetric U-Net; here a small
  dense 3-D U-Net (:class:`DenseUNet3d`) stands in, so that CPU runs at coarse grids work.
"""

from __future__ import annotations

from torch import Tensor, nn

from distilkit_adapters._blocks import DenseUNet3d, PointVoxelizer


class ConvBlock(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int) -> None:
        super().__init__(nn.Conv3d(cin, cout, k, padding=k // 2, bias=False), nn.ReLU(inplace=False))


class MultiPathBlock(nn.Module):
    """Parallel 3/5/7 ConvBlocks, concatenated, fused by a 1x1x1 ConvBlock (no bias, no BN)."""

    def __init__(self, c: int, kernels: tuple[int, ...] = (3, 5, 7)) -> None:
        super().__init__()
        self.paths = nn.ModuleList(ConvBlock(c, c, k) for k in kernels)
        self.fuse = ConvBlock(c * len(kernels), c, 1)

    def forward(self, x: Tensor) -> Tensor:
        import torch

        return self.fuse(torch.cat([p(x) for p in self.paths], dim=1))


class CompletionSubNetwork(nn.Module):
    """upper = MPB(x); middle = Conv3(MPB(MPB(Conv3(x)))); out = upper + middle + x."""

    def __init__(self, c: int) -> None:
        super().__init__()
        self.upper = MultiPathBlock(c)
        self.middle = nn.Sequential(ConvBlock(c, c, 3), MultiPathBlock(c), MultiPathBlock(c), ConvBlock(c, c, 3))

    def forward(self, x: Tensor) -> Tensor:
        return self.upper(x) + self.middle(x) + x


class SCPNet(nn.Module):
    def __init__(self, channels: int, point_mlp: list[int], seg_channels: int, num_classes: int) -> None:
        super().__init__()
        self.voxelizer = PointVoxelizer(point_mlp, channels)
        self.completion = CompletionSubNetwork(channels)
        self.segmentation = DenseUNet3d(channels, seg_channels, num_classes)
