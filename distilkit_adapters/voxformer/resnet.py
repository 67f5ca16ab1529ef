"""VoxFormer's image encoder at ``encoder: resnet50``: ResNet-50 (He et al. CVPR 2016; bottleneck blocks with the
stride in the 3x3 convolution, torchvision's "v1.5") up to its third stage (1024 channels, stride 16) and a one-level
FPN (Lin et al. CVPR 2017) to ``channels`` (VoxFormer: 128).

Module names are torchvision's (``conv1``, ``bn1``, ``layer1.0.conv1``, ``layer1.0.downsample.0``, ...) under
``backbone.``, so an ImageNet file (``resnet50-19c8e357.pth``) loads as it is (:mod:`.weights`); the FPN's are
``lateral_convs.0.conv`` / ``fpn_convs.0.conv`` (mmdet's). As VoxFormer trains it (its configs, read as facts): the
batch norms are frozen (running statistics kept, no gradient), and so are the stem and the first stage; the fourth
stage is not built (VoxFormer reads the third only). Images are normalised with ImageNet's mean and spread, as
VoxFormer's loader does.
"""

from __future__ import annotations

from torch import Tensor, nn

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
BLOCKS = (3, 4, 6)  # ResNet-50's blocks in its first three stages
STRIDE = 16


class Bottleneck(nn.Module):
    """1x1 -> 3x3 (stride) -> 1x1 (x4 channels), batch norms, and a projected shortcut where the shape changes."""

    def __init__(self, cin: int, width: int, stride: int) -> None:
        super().__init__()
        cout = 4 * width
        self.conv1 = nn.Conv2d(cin, width, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(width)
        self.conv2 = nn.Conv2d(width, width, 3, stride, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(width)
        self.conv3 = nn.Conv2d(width, cout, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(cout)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = (nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
                           if stride != 1 or cin != cout else None)

    def forward(self, x: Tensor) -> Tensor:
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


class ResNet50(nn.Module):
    """Stem and stages 1-3 of ResNet-50: (N, 3, H, W) normalised images -> (N, 1024, H/16, W/16)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, 7, 2, 3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        cin = 64
        for i, (blocks, width) in enumerate(zip(BLOCKS, (64, 128, 256))):
            stage = []
            for j in range(blocks):
                stage.append(Bottleneck(cin, width, 2 if j == 0 and i > 0 else 1))
                cin = 4 * width
            setattr(self, f"layer{i + 1}", nn.Sequential(*stage))
        self.out_channels = cin
        frozen = [self.conv1, self.bn1, self.layer1] + [m for m in self.modules() if isinstance(m, nn.BatchNorm2d)]
        for module in frozen:
            for p in module.parameters():
                p.requires_grad_(False)

    def train(self, mode: bool = True) -> "ResNet50":
        """Training mode, but the batch norms keep their running statistics (VoxFormer's ``norm_eval``)."""
        super().train(mode)
        for m in self.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        return self

    def forward(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer3(self.layer2(self.layer1(x)))


class ConvModule(nn.Module):
    """A convolution under the name ``conv`` (the FPN's modules' layout)."""

    def __init__(self, cin: int, cout: int, kernel: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, 1, kernel // 2)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x)


class FPN(nn.Module):
    """A one-level FPN: a 1x1 lateral convolution to ``channels``, then a 3x3 output convolution."""

    def __init__(self, cin: int, channels: int) -> None:
        super().__init__()
        self.lateral_convs = nn.ModuleList([ConvModule(cin, channels, 1)])
        self.fpn_convs = nn.ModuleList([ConvModule(channels, channels, 3)])

    def forward(self, x: Tensor) -> Tensor:
        return self.fpn_convs[0](self.lateral_convs[0](x))


def frozen_fraction(module: nn.Module) -> float:
    """The share of ``module``'s weights that take no gradient (a check for tests and the bench)."""
    total = sum(p.numel() for p in module.parameters())
    return sum(p.numel() for p in module.parameters() if not p.requires_grad) / max(total, 1)


__all__ = ["BLOCKS", "Bottleneck", "FPN", "IMAGENET_MEAN", "IMAGENET_STD", "ResNet50", "STRIDE", "frozen_fraction"]
