"""VoxFormer's deformable self-attention over the whole query volume (Li et al. CVPR 2023, §3.3 and eq. 4; Zhu et
al. ICLR 2021): each query predicts, per head, ``points`` sampling offsets around its own position and one weight
per point (a softmax over the points); the heads' values are read there (bilinear or trilinear, zero outside) and
summed with the weights. A layer: ``x = norm1(x + out(DSA(x + pos)))``, ``x = norm2(x + FFN(x))``.

Where the values are read (``space``), as the paper and its release differ:

* ``3d`` (default): offsets in voxels around the query's own voxel of the (X, Y, Z) volume — the paper's §3.3
  ("deformable self-attention ... over the voxel queries") and the release's ``*_deform3D`` configs;
* ``plane``: the release's VoxFormer-S/T configs (BEVFormer's 2-D deformable attention): the X*Y*Z queries, in their
  flat order, reshaped to a plane (the release: 262 144 = 512 x 512) and attended in 2-D; neighbours on that plane
  are not neighbours in space across its rows.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def plane_shape(n: int) -> tuple[int, int]:
    """The (rows, columns) of the plane the ``plane`` space reshapes ``n`` queries to: the most square factors
    (262 144 -> 512 x 512, VoxFormer's)."""
    rows = max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)
    return rows, n // rows


def reference(shape: tuple[int, ...], device: torch.device) -> Tensor:
    """(N, d) grid_sample coordinates (-1..1, last axis first) of the centres of a ``shape`` volume or plane, in the
    flat order of its cells."""
    axes = [(torch.arange(s, device=device, dtype=torch.float32) + 0.5) / s * 2 - 1 for s in shape]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).view(-1, len(shape))
    return grid.flip(-1)  # grid_sample's order: the last (fastest) axis first


class DeformableSelfAttention(nn.Module):
    """One deformable self-attention layer (with its residuals, layer norms and FFN) over a dense query volume."""

    def __init__(self, channels: int, heads: int, points: int, space: str = "3d") -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"channels ({channels}) must be divisible by heads ({heads})")
        if space not in ("3d", "plane"):
            raise ValueError(f"space must be '3d' or 'plane', got {space!r}")
        self.heads, self.points, self.space = heads, points, space
        self.dims = 3 if space == "3d" else 2
        self.offsets = nn.Linear(channels, heads * points * self.dims)
        self.weights = nn.Linear(channels, heads * points)
        self.value = nn.Linear(channels, channels)
        self.out = nn.Linear(channels, channels)
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = nn.Sequential(nn.Linear(channels, 2 * channels), nn.ReLU(), nn.Linear(2 * channels, channels))
        self.norm2 = nn.LayerNorm(channels)
        nn.init.zeros_(self.offsets.weight)  # start on a ring (a sphere's directions in 3-D) of one cell around it
        with torch.no_grad():
            k = torch.arange(heads * points, dtype=torch.float32) + 0.5
            if self.dims == 2:
                angle = k * (2 * torch.pi / (heads * points))
                ring = torch.stack([angle.cos(), angle.sin()], -1)
            else:  # a Fibonacci sphere
                z = 1 - 2 * k / (heads * points)
                angle = k * torch.pi * (3 - math.sqrt(5))
                r = (1 - z * z).clamp_min(0).sqrt()
                ring = torch.stack([r * angle.cos(), r * angle.sin(), z], -1)
            self.offsets.bias.copy_(ring.reshape(-1))

    def cells(self, shape: tuple[int, int, int]) -> tuple[int, ...]:
        """The cells the values live on: the volume, or the plane its flat queries fold to."""
        return shape if self.space == "3d" else plane_shape(shape[0] * shape[1] * shape[2])

    def forward(self, volume: Tensor, pos: Tensor) -> Tensor:
        """``volume`` (B, C, X, Y, Z) queries, ``pos`` (X*Y*Z, C) their positional encodings -> (B, C, X, Y, Z)."""
        b, c, *shape = volume.shape
        cells = self.cells(tuple(shape))  # type: ignore[arg-type]
        n, hd, p, d = volume[0, 0].numel(), self.heads, self.points, self.dims
        x = volume.flatten(2).transpose(1, 2)  # (B, N, C)
        q = x + pos
        size = volume.new_tensor(cells[::-1])  # cells per grid_sample axis (last axis first)
        ref = reference(cells, volume.device).to(volume.dtype)  # (N, d)
        where = ref[None, :, None, None, :] + self.offsets(q).view(b, n, hd, p, d) * 2 / size  # offsets in cells
        attn = self.weights(q).view(b, n, hd, p).softmax(-1)
        values = self.value(x).view(b, n, hd, c // hd).permute(0, 2, 3, 1).reshape(b * hd, c // hd, *cells)
        grid = where.permute(0, 2, 1, 3, 4).reshape(b * hd, n, p, *([1] * (d - 2)), d)
        sampled = F.grid_sample(values, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        sampled = sampled.view(b, hd, c // hd, n, p)
        read = torch.einsum("bhcnp,bnhp->bnhc", sampled, attn).reshape(b, n, c)
        x = self.norm1(x + self.out(read))
        x = self.norm2(x + self.ffn(x))
        return x.transpose(1, 2).reshape(b, c, *shape)


__all__ = ["DeformableSelfAttention", "plane_shape", "reference"]
