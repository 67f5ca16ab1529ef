"""LiDiff's networks at the paper's size (PRBonn/LiDiff ``models/minkunet.py``), on :mod:`distilkit.sparse` instead of
MinkowskiEngine, with the release's module names so that its checkpoints load (``convert.read_lidiff``):

* ``MinkGlobalEnc`` — the scan encoder: stem (two 3^3 convolutions) and four stages of a 2^3 stride-2 convolution
  and two residual blocks, channels 32, 32, 64, 128, 256: 256-channel features at stride 16 (0.8 m voxels);
* ``MinkUNetDiff`` — the denoiser over the noisy points (5 cm voxels, features = the points' mean position): the
  same encoder shape, four up levels (2^3 transposed convolution, concatenation with the encoder level, two
  residual blocks; channels 256, 128, 96, 96), and before each of the eight levels the multiplicative conditioning
  x * w, w = MLP([MLP(nearest scan feature), MLP(timestep embedding)]); each point reads its voxel's features back
  (``slice``), then Linear(96 -> 20), LeakyReLU(0.1), Linear(20 -> 3): the predicted noise per point;
* ``MinkUNet`` — the refinement network: the same U-Net without conditioning, ending in 18 outputs and tanh (six
  offsets per point).

MinkowskiEngine's semantics kept: a stride-1 convolution keeps its input's sites (submanifold), a 2^3 stride-2 one
takes sites to floor(c / 2), a transposed one goes back onto the encoder level's sites (``ME.cat`` then joins features
of one site); batch norms over every active voxel; the nearest scan feature found among the same scene's encoder
voxels in 5 cm units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from distilkit.geometry.nearest import nearest
from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d
from distilkit.sparse.points import voxelize

RESOLUTION = 0.05  # LiDiff's voxel (m)
CHANNELS = (32, 32, 64, 128, 256, 256, 128, 96, 96)
STRIDE = 16  # the encoder's output stride


def conv(inc: int, outc: int, ks: int, stride: int = 1, key: str | None = None) -> nn.Module:
    """``ME.MinkowskiConvolution(inc, outc, ks, stride)`` (no bias): stride 1 keeps the sites; stride ``ks`` = 2 is a
    strided convolution whose map ``key`` names (its transposed partner inverts it)."""
    if stride == 1:
        return SubMConv3d(inc, outc, ks, bias=False, indice_key=key)
    return SparseConv3d(inc, outc, ks, stride=stride, bias=False, indice_key=key)


class MinkBatchNorm(nn.Module):
    """``ME.MinkowskiBatchNorm``: BatchNorm1d (under ``.bn``) over the features of every active voxel."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.bn = nn.BatchNorm1d(channels)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return x.replace_feature(self.bn(x.features))


class MinkReLU(nn.Module):
    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return x.replace_feature(torch.relu(x.features))


class BasicConvolutionBlock(nn.Module):
    def __init__(self, inc: int, outc: int, ks: int = 3, stride: int = 1, key: str | None = None) -> None:
        super().__init__()
        self.net = nn.Sequential(conv(inc, outc, ks, stride, key), MinkBatchNorm(outc), MinkReLU())

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return self.net(x)


class BasicDeconvolutionBlock(nn.Module):
    """``ME.MinkowskiConvolutionTranspose(ks, stride)`` back onto the sites of the strided convolution ``key``."""

    def __init__(self, inc: int, outc: int, ks: int, key: str) -> None:
        super().__init__()
        self.net = nn.Sequential(SparseInverseConv3d(inc, outc, ks, indice_key=key, bias=False), MinkBatchNorm(outc),
                                 MinkReLU())

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return self.net(x)


class ResidualBlock(nn.Module):
    def __init__(self, inc: int, outc: int, ks: int = 3, key: str | None = None) -> None:
        super().__init__()
        self.net = nn.Sequential(conv(inc, outc, ks, key=key), MinkBatchNorm(outc), MinkReLU(),
                                 conv(outc, outc, ks, key=key), MinkBatchNorm(outc))
        self.downsample = nn.Sequential() if inc == outc else nn.Sequential(conv(inc, outc, 1, key=f"{key}_1"),
                                                                            MinkBatchNorm(outc))
        self.relu = MinkReLU()

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        out = self.net(x)
        skip = self.downsample(x) if len(self.downsample) else x
        return self.relu(out.replace_feature(out.features + skip.features))


def _stage(inc: int, mid: int, out: int, level: int) -> nn.Sequential:
    """A 2^3 stride-2 convolution (map ``down{level}``) and two residual blocks at the next level."""
    return nn.Sequential(BasicConvolutionBlock(inc, mid, ks=2, stride=2, key=f"down{level}"),
                         ResidualBlock(mid, out, key=f"subm{level}"), ResidualBlock(out, out, key=f"subm{level}"))


def _stem(inc: int, out: int) -> nn.Sequential:
    return nn.Sequential(conv(inc, out, 3, key="subm0"), MinkBatchNorm(out), MinkReLU(),
                         conv(out, out, 3, key="subm0"), MinkBatchNorm(out), MinkReLU())


def _up(inc: int, out: int, skip: int, level: int) -> nn.ModuleList:
    """Up to level ``level``: the transposed convolution of map ``down{level + 1}``, then two residual blocks on
    [its output, the encoder level]."""
    return nn.ModuleList([BasicDeconvolutionBlock(inc, out, 2, key=f"down{level + 1}"),
                          nn.Sequential(ResidualBlock(out + skip, out, key=f"subm{level}"),
                                        ResidualBlock(out, out, key=f"subm{level}"))])


def _add_levels(module: nn.Module, cs: list[int], decoder: bool) -> None:
    """The four down stages (``stage1``..``stage4``) and, with ``decoder``, the four up stages (``up1``..``up4``) of
    channel widths ``cs``, under the release's names."""
    for level in range(1, 5):
        setattr(module, f"stage{level}", _stage(cs[level - 1], cs[level - 1], cs[level], level))
    if decoder:
        for i in range(1, 5):
            setattr(module, f"up{i}", _up(cs[3 + i], cs[4 + i], cs[4 - i], 4 - i))


def _mlp(a: int, b: int, c: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(a, b), nn.LeakyReLU(0.1, inplace=True), nn.Linear(b, c))


@dataclass
class EncodedScan:
    """The scan encoder's output: 256-channel features, their coordinates in 5 cm units and their scene."""

    features: Tensor
    coords: Tensor  # (V, 3) float
    batch: Tensor  # (V,) int64


class MinkGlobalEnc(nn.Module):
    """LiDiff's scan encoder (``partial_enc``)."""

    def __init__(self, in_channels: int = 3, cr: float = 1.0) -> None:
        super().__init__()
        cs = [int(cr * c) for c in CHANNELS]
        self.stem = _stem(in_channels, cs[0])
        _add_levels(self, cs, decoder=False)

    def forward(self, scan: Tensor) -> EncodedScan:
        vox = voxelize(scan, RESOLUTION, align=STRIDE)
        x = self.stage4(self.stage3(self.stage2(self.stage1(self.stem(vox.tensor)))))
        return EncodedScan(x.features, vox.coordinates(x.indices, STRIDE), x.indices[:, 0].long())


def timestep_embedding(t: Tensor, dim: int) -> Tensor:
    """LiDiff's sinusoidal embedding: [sin, cos] of t exp(-i ln(10^4) / (dim/2 - 1)), i < dim/2."""
    half = dim // 2
    freqs = torch.exp(torch.arange(half, device=t.device, dtype=torch.float64) * -(math.log(10000) / (half - 1)))
    args = t.float()[:, None] * freqs.float()[None]  # float32, as the release multiplies
    emb = torch.cat([torch.sin(args), torch.cos(args)], dim=1)
    return nn.functional.pad(emb, (0, 1)) if dim % 2 else emb


class MinkUNetDiff(nn.Module):
    """LiDiff's denoiser (``model``): eps_hat of every noisy point, conditioned on the encoded scan and t."""

    LEVELS = (("stage1", "stage1_temp", "latent_stage1", "latemp_stage1"),
              ("stage2", "stage2_temp", "latent_stage2", "latemp_stage2"),
              ("stage3", "stage3_temp", "latent_stage3", "latemp_stage3"),
              ("stage4", "stage4_temp", "latent_stage4", "latemp_stage4"),
              ("up1", "up1_temp", "latent_up1", "latemp_up1"), ("up2", "up2_temp", "latent_up2", "latemp_up2"),
              ("up3", "up3_temp", "latent_up3", "latemp_up3"), ("up4", "up4_temp", "latent_up4", "latemp_up4"))

    def __init__(self, in_channels: int = 3, cr: float = 1.0) -> None:
        super().__init__()
        cs = [int(cr * c) for c in CHANNELS]
        self.embed_dim = cs[-1]
        self.stem = _stem(in_channels, cs[0])
        widths = {"stage1": cs[0], "stage2": cs[1], "stage3": cs[2], "stage4": cs[3], "up1": cs[4], "up2": cs[5],
                  "up3": cs[6], "up4": cs[7]}
        for name, temp, latent, latemp in self.LEVELS:
            setattr(self, latent, _mlp(cs[4], cs[4], cs[4]))
            out = widths[name]
            hidden = cs[4] if name.startswith("stage") or name == "up1" else out
            setattr(self, latemp, _mlp(cs[4] + cs[4], hidden, out))
            setattr(self, temp, _mlp(self.embed_dim, self.embed_dim, cs[4]))
        _add_levels(self, cs, decoder=True)
        self.last = nn.Sequential(nn.Linear(cs[8], 20), nn.LeakyReLU(0.1, inplace=True), nn.Linear(20, 3))

    def _weights(self, level: int, x: SparseConvTensor, stride: int, vox, enc: EncodedScan, temb: Tensor) -> Tensor:
        """w of level ``level``: latemp([latent(nearest scan feature), temp(t)]) (up1: [temp, latent], as released)."""
        name, temp, latent, latemp = self.LEVELS[level]
        batch = x.indices[:, 0].long()
        coords = vox.coordinates(x.indices, stride)
        matched = torch.empty((len(coords), enc.features.shape[1]), device=coords.device, dtype=enc.features.dtype)
        for b in torch.unique(batch).tolist():
            mine, theirs = batch == b, enc.batch == b
            matched[mine] = enc.features[theirs][nearest(coords[mine], enc.coords[theirs])]
        p = getattr(self, latent)(matched)
        t = getattr(self, temp)(temb)[batch]
        return getattr(self, latemp)(torch.cat((t, p) if name == "up1" else (p, t), dim=-1))

    def forward(self, x_t: Tensor, t: Tensor, enc: EncodedScan) -> Tensor:
        """(B, M, 3) noisy points, (B,) timesteps, the encoded scan -> (B, M, 3) predicted noise."""
        vox = voxelize(x_t, RESOLUTION, align=STRIDE)
        temb = timestep_embedding(t, self.embed_dim).to(x_t.dtype)  # float32 products, as released
        scale = lambda x, level, stride: x.replace_feature(  # noqa: E731
            x.features * self._weights(level, x, stride, vox, enc, temb))
        x0 = self.stem(vox.tensor)
        x1 = self.stage1(scale(x0, 0, 1))
        x2 = self.stage2(scale(x1, 1, 2))
        x3 = self.stage3(scale(x2, 2, 4))
        x4 = self.stage4(scale(x3, 3, 8))
        y = x4
        for level, (up, skip, stride) in enumerate(((self.up1, x3, 16), (self.up2, x2, 8), (self.up3, x1, 4),
                                                    (self.up4, x0, 2)), start=4):
            y = up[0](scale(y, level, stride))
            y = up[1](y.replace_feature(torch.cat([y.features, skip.features], dim=1)))  # ME.cat: same sites
        return self.last(vox.slice(y.features)).view(x_t.shape)


class MinkUNet(nn.Module):
    """LiDiff's refinement network (``model_refine``): the U-Net without conditioning, tanh outputs per point."""

    def __init__(self, in_channels: int = 3, out_channels: int = 18, cr: float = 1.0) -> None:
        super().__init__()
        cs = [int(cr * c) for c in CHANNELS]
        self.stem = _stem(in_channels, cs[0])
        _add_levels(self, cs, decoder=True)
        self.last = nn.Sequential(nn.Linear(cs[8], 20), nn.LeakyReLU(0.1, inplace=True), nn.Linear(20, out_channels),
                                  nn.Tanh())

    def forward(self, points: Tensor) -> Tensor:
        """(B, M, 3) points -> (B, M, out_channels)."""
        vox = voxelize(points, RESOLUTION, align=STRIDE)
        x0 = self.stem(vox.tensor)
        x1 = self.stage1(x0)
        x2 = self.stage2(x1)
        x3 = self.stage3(x2)
        y = self.stage4(x3)
        for up, skip in ((self.up1, x3), (self.up2, x2), (self.up3, x1), (self.up4, x0)):
            y = up[0](y)
            y = up[1](y.replace_feature(torch.cat([y.features, skip.features], dim=1)))
        return self.last(vox.slice(y.features)).view(*points.shape[:2], -1)


class LiDiffNet(nn.Module):
    """The paper-size denoiser as the LiDiff adapter calls it: ``net(x_t, t, scan, enc)`` and ``net.encoder(scan)``
    (the same interface as the CPU stand-in), the release's ``partial_enc`` and ``model`` inside."""

    def __init__(self) -> None:
        super().__init__()
        self.partial_enc = MinkGlobalEnc()
        self.model = MinkUNetDiff()

    @property
    def encoder(self) -> MinkGlobalEnc:
        return self.partial_enc

    def forward(self, x_t: Tensor, t: Tensor, scan: Tensor, enc: EncodedScan | None = None) -> Tensor:
        return self.model(x_t, t, self.partial_enc(scan) if enc is None else enc)


__all__ = ["EncodedScan", "LiDiffNet", "MinkGlobalEnc", "MinkUNet", "MinkUNetDiff", "timestep_embedding"]
