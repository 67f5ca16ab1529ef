"""The image encoder of the VoxFormer-style models: a small ResNet (basic blocks, each stage halving the resolution)
and a one-level FPN (Lin et al. CVPR 2017) that fuses the last stage into the one before it.

VoxFormer uses ResNet-50's stage 3 (stride 16) with a 128-channel FPN level; here the widths and so the output
stride (2 ** (number of stages - 1)) are parameters, so a CPU test uses a few thousand weights and a GPU the paper's
size.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn


class BasicBlock(nn.Module):
    """Two 3x3 convolutions with batch norm and a (projected) shortcut (He et al. CVPR 2016)."""

    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)
        self.skip = (nn.Identity() if stride == 1 and cin == cout else
                     nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout)))

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.bn1(self.conv1(x)))
        return F.relu(self.bn2(self.conv2(y)) + self.skip(x))


class ImageEncoder(nn.Module):
    """(N, 3, H, W) images in 0..1 -> (N, channels, H / s, W / s) features, s = 2 ** (len(widths) - 1)."""

    def __init__(self, widths: list[int], channels: int) -> None:
        super().__init__()
        if len(widths) < 2:
            raise ValueError(f"the image encoder needs at least two stages (widths), got {widths}")
        self.stem = nn.Sequential(nn.Conv2d(3, widths[0], 3, 2, 1, bias=False), nn.BatchNorm2d(widths[0]), nn.ReLU())
        self.stages = nn.ModuleList(BasicBlock(widths[max(i - 1, 0)], w, 1 if i == 0 else 2)
                                    for i, w in enumerate(widths))
        self.lateral = nn.ModuleList([nn.Conv2d(widths[-2], channels, 1), nn.Conv2d(widths[-1], channels, 1)])
        self.output = nn.Conv2d(channels, channels, 3, 1, 1)
        self.stride = 2 ** (len(widths) - 1)

    def forward(self, images: Tensor) -> Tensor:
        x = (images - 0.45) / 0.25  # about zero mean, unit spread
        x = self.stem(x)
        feats = []
        for stage in self.stages:
            x = stage(x)
            feats.append(x)
        top = self.lateral[1](feats[-1])
        fused = self.lateral[0](feats[-2]) + F.interpolate(top, size=feats[-2].shape[-2:], mode="nearest")
        return self.output(fused)


__all__ = ["BasicBlock", "ImageEncoder"]
