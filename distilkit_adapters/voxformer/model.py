"""A VoxFormer-style camera SSC network (Li et al. CVPR 2023), stage 2, written from the paper's description.

Images of one or more frames -> image encoder + FPN -> voxel queries on the half-resolution grid: the proposed
(occupied) ones read the image features by deformable cross-attention around their centres' projections, the others
take a shared mask embedding -> 3-D mixing -> completion head: trilinear x2 to the full grid, LayerNorm + Linear to
class scores. This is the CPU stand-in (``size: tiny``): a small ResNet image encoder, the queries mixed by residual
3-D convolutions (``mixing: conv``) or by VoxFormer's deformable self-attention layers (``mixing: deformable-plane |
deformable-3d``, :mod:`.deformable`); the released network is :mod:`.release`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from distilkit.structures import SparseVoxels, VoxelGrid
from distilkit_adapters.voxformer.attention import DeformableCrossAttention, project
from distilkit_adapters.voxformer.backbone import ImageEncoder
from distilkit_adapters.voxformer.transformer import self_layer

MIXINGS = ("conv", "deformable-3d", "deformable-plane")


class MixBlock(nn.Module):
    """A residual 3x3x3 convolution block over the dense query volume."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv3d(channels, channels, 3, 1, 1, bias=False), nn.BatchNorm3d(channels),
                                  nn.ReLU(), nn.Conv3d(channels, channels, 3, 1, 1, bias=False),
                                  nn.BatchNorm3d(channels))

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(x + self.conv(x))


class VoxFormerNet(nn.Module):
    """The stage-2 network on ``grid`` (the full SSC grid); queries live on ``grid.coarsen(2)``."""

    def __init__(self, widths: list[int], channels: int, heads: int, points: int, frames: int, cross_layers: int,
                 mix_layers: int, num_classes: int, grid: VoxelGrid, mixing: str = "conv") -> None:
        super().__init__()
        if mixing not in MIXINGS:
            raise ValueError(f"mixing must be one of {', '.join(MIXINGS)}, got {mixing!r}")
        self.grid, self.query_grid = grid, grid.coarsen(2)
        self.encoder = ImageEncoder(widths, channels)
        self.queries = nn.Embedding(int(torch.tensor(self.query_grid.shape).prod()), channels)
        self.pos = nn.Sequential(nn.Linear(3, channels), nn.ReLU(), nn.Linear(channels, channels))
        self.mask_embed = nn.Parameter(torch.zeros(channels))
        self.cross = nn.ModuleList(DeformableCrossAttention(channels, heads, points, frames) for _ in range(cross_layers))
        self.mixing = mixing
        self.mix = (nn.Sequential(*(MixBlock(channels) for _ in range(mix_layers))) if mixing == "conv" else
                    nn.ModuleList(self_layer(channels, heads, points, 2 * channels, mixing.split("-")[1])
                                  for _ in range(mix_layers)))
        self.norm = nn.LayerNorm(channels)
        self.classifier = nn.Linear(channels, num_classes)

    def positions(self, idx: Tensor) -> Tensor:
        """(M, C) positional encodings of query indices (M, 3): an MLP of the centres scaled to about -1..1."""
        shape = torch.tensor(self.query_grid.shape, device=idx.device, dtype=torch.float32)
        return self.pos((idx.float() + 0.5) / shape * 2 - 1)

    def forward(self, images: Tensor, intrinsics: Tensor, to_camera: Tensor,
                occupied: Tensor) -> tuple[Tensor, SparseVoxels, Tensor]:
        """``images`` (B, T, 3, H, W), calibration (B, T, 3, 3) / (B, T, 4, 4), ``occupied`` (B, X/2, Y/2, Z/2)
        bool proposals. Returns image features (B, T, C, h, w), the proposed queries after cross-attention (sparse
        voxels on the query grid) and class scores (B, K, X, Y, Z)."""
        b, t = images.shape[:2]
        feats = self.encoder(images.flatten(0, 1))
        feats = feats.view(b, t, *feats.shape[1:])
        coords = torch.nonzero(occupied)  # (N, 4): batch, x, y, z
        x, y, z = self.query_grid.shape
        flat = (coords[:, 1] * y + coords[:, 2]) * z + coords[:, 3]
        sample = coords[:, 0]
        pixels, seen = project(self.query_grid.centers(coords[:, 1:]), intrinsics[sample], to_camera[sample],
                               tuple(images.shape[-2:]))
        q, pos = self.queries.weight[flat], self.positions(coords[:, 1:])
        for layer in self.cross:
            q = layer(q, pos, sample, pixels, seen, feats, tuple(images.shape[-2:]))
        grid_idx = torch.stack(torch.meshgrid(*(torch.arange(s, device=images.device) for s in (x, y, z)),
                                              indexing="ij"), -1).view(-1, 3)
        grid_pos = self.positions(grid_idx)
        conv = self.mixing == "conv"  # convolutions see the positions in the volume; attention adds them itself
        base = self.mask_embed + grid_pos if conv else self.mask_embed.expand(len(grid_idx), -1)
        volume = base.reshape(1, x, y, z, -1).repeat(b, 1, 1, 1, 1)
        volume = volume.index_put((sample, coords[:, 1], coords[:, 2], coords[:, 3]), q + pos if conv else q)
        mixed = volume.permute(0, 4, 1, 2, 3)
        if conv:
            mixed = self.mix(mixed)
        else:  # VoxFormer: the query volume attends to itself
            flat = mixed.flatten(2).transpose(1, 2)
            for layer in self.mix:
                flat = layer.finish(layer.attentions[0](flat, grid_pos, (x, y, z)))
            mixed = flat.transpose(1, 2).reshape(b, -1, x, y, z)
        up = F.interpolate(mixed, scale_factor=2, mode="trilinear", align_corners=False)
        logits = self.classifier(self.norm(up.permute(0, 2, 3, 4, 1))).permute(0, 4, 1, 2, 3)
        return feats, SparseVoxels(coords, q, self.query_grid.shape, self.query_grid), logits


__all__ = ["MixBlock", "VoxFormerNet"]
