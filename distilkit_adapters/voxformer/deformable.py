"""VoxFormer's deformable attention modules as its release computes them (NVlabs/VoxFormer,
``modules/deformable_cross_attention.py``, ``deformable_self_attention.py``, ``deformable_self_attention_3D_custom.py``;
written here from those facts, with the release's parameter names so that its checkpoint loads):

* :func:`deformable_read` — multi-scale deformable attention's sampling with one level (Zhu et al. ICLR 2021; mmcv's
  ``multi_scale_deformable_attn_pytorch`` and VoxFormer's 3-D CUDA kernel): per head, the values at normalised
  locations (bilinear on (h, w) / trilinear on (h, w, z) at location x size - 0.5, zero outside: ``grid_sample``
  with ``align_corners=False``), summed with the attention weights. A location's components are (w, h) in 2-D and
  (w, h, z) in 3-D, the value's cells flat in (h, w[, z]) order.
* :class:`MSDeformableAttention3D` — ``sampling_offsets`` (heads x points x 2, in feature-map pixels),
  ``attention_weights`` (a softmax over each head's points), ``value_proj``; no output projection.
* :class:`DeformCrossAttention` — the queries seen by each image attend to it around their reference point's
  projection (the same offsets and weights in every image: one ``deformable_attention`` for all), the reads summed
  over the images that see the query and divided by their number (at least 1); ``output_proj`` on every query
  (one seen by no image gets its bias), dropout, plus the query (the residual). No positional encoding: the release's
  ``VoxFormerLayer`` passes ``query_pos=None`` to it.
* :class:`DeformSelfAttention` — ``num_bev_queue`` = 2: the value is the query twice (no previous frame), the offsets
  and weights are predicted from [query, query + position] (2C channels), one set per queue, and the two reads are
  averaged; ``output_proj``, dropout, plus the query. ``space``: ``plane`` (VoxFormer-S/T, whose checkpoints are
  released: the X*Y*Z queries in their flat order folded to a plane, 512 x 512 at 128 x 128 x 16, attended in 2-D
  around ((column + 0.5) / W, (row + 0.5) / H)) or ``3d`` (the ``*_deform3D`` configs: trilinear in the (X, Y, Z)
  volume around ((y + 0.5) / Y, (x + 0.5) / X, (z + 0.5) / Z), offsets normalised by (Y, X, Z); the release passes
  this layer a 2-D spatial shape, which its 3-D attention cannot index, so the volume's is taken).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def deformable_read(value: Tensor, shape: tuple[int, ...], locations: Tensor, weights: Tensor) -> Tensor:
    """``value`` (B, Nv, heads, Cd) on cells ``shape`` ((h, w) or (h, w, z), flat in that order), ``locations``
    (B, N, heads, P, d) in 0..1 ((w, h) or (w, h, z)), ``weights`` (B, N, heads, P) -> (B, N, heads * Cd)."""
    b, nv, heads, cd = value.shape
    n, p, d = locations.shape[1], locations.shape[3], locations.shape[4]
    v = value.permute(0, 2, 3, 1).reshape(b * heads, cd, *shape)
    grid = locations.permute(0, 2, 1, 3, 4).reshape(b * heads, n, p, d) * 2 - 1
    if d == 3:  # grid_sample's 5-D order: (x, y, z) = the last, middle and first axis of (h, w, z)
        grid = torch.stack([grid[..., 2], grid[..., 0], grid[..., 1]], -1)[:, :, :, None]
    sampled = F.grid_sample(v, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    sampled = sampled.reshape(b, heads, cd, n, p)
    return torch.einsum("bhcnp,bnhp->bnhc", sampled, weights).reshape(b, n, heads * cd)


def _ring(heads: int, groups: int, points: int) -> Tensor:
    """The release's initial sampling offsets: per head a direction on the unit square's edge, the i-th point at
    i + 1 times it, for ``groups`` (levels x queues)."""
    theta = torch.arange(heads, dtype=torch.float32) * (2 * math.pi / heads)
    grid = torch.stack([theta.cos(), theta.sin()], -1)
    grid = (grid / grid.abs().max(-1, keepdim=True).values).view(heads, 1, 1, 2).repeat(1, groups, points, 1)
    return grid * torch.arange(1, points + 1, dtype=torch.float32).view(1, 1, points, 1)


def _xavier(linear: nn.Linear) -> None:
    nn.init.xavier_uniform_(linear.weight)
    nn.init.zeros_(linear.bias)


class MSDeformableAttention3D(nn.Module):
    """One image level's deformable attention around reference points (B, N, 2) in 0..1 of the image."""

    def __init__(self, embed_dims: int, num_heads: int = 8, num_points: int = 8) -> None:
        super().__init__()
        if embed_dims % num_heads:
            raise ValueError(f"channels ({embed_dims}) must be divisible by heads ({num_heads})")
        self.heads, self.points = num_heads, num_points
        self.sampling_offsets = nn.Linear(embed_dims, num_heads * num_points * 2)
        self.attention_weights = nn.Linear(embed_dims, num_heads * num_points)
        self.value_proj = nn.Linear(embed_dims, embed_dims)
        nn.init.zeros_(self.sampling_offsets.weight)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(_ring(num_heads, 1, num_points).reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        _xavier(self.value_proj)

    def forward(self, query: Tensor, value: Tensor, reference: Tensor, shape: tuple[int, int]) -> Tensor:
        """``query`` (B, N, C), ``value`` (B, h * w, C) on ``shape`` (h, w), ``reference`` (B, N, 2) -> (B, N, C)."""
        b, n, _ = query.shape
        v = self.value_proj(value).view(b, value.shape[1], self.heads, -1)
        offsets = self.sampling_offsets(query).view(b, n, self.heads, self.points, 2)
        weights = self.attention_weights(query).view(b, n, self.heads, self.points).softmax(-1)
        norm = offsets.new_tensor([shape[1], shape[0]])
        locations = reference[:, :, None, None, :] + offsets / norm
        return deformable_read(v, shape, locations, weights)


class DeformCrossAttention(nn.Module):
    """The proposed queries read the T images' features (the release's spatial cross-attention)."""

    def __init__(self, embed_dims: int, num_heads: int = 8, num_points: int = 8, dropout: float = 0.1) -> None:
        super().__init__()
        self.deformable_attention = MSDeformableAttention3D(embed_dims, num_heads, num_points)
        self.output_proj = nn.Linear(embed_dims, embed_dims)
        self.dropout = nn.Dropout(dropout)
        _xavier(self.output_proj)

    def forward(self, query: Tensor, values: Tensor, reference: Tensor, seen: Tensor, shape: tuple[int, int]) -> Tensor:
        """``query`` (N, C) of one sample, ``values`` (T, h * w, C) its images' features, ``reference`` (T, N, 2)
        the queries' projections in 0..1 and ``seen`` (T, N) where they fall inside the image -> (N, C)."""
        slots = torch.zeros_like(query)
        for t in range(values.shape[0]):
            rows = seen[t].nonzero().squeeze(1)
            if rows.numel():
                read = self.deformable_attention(query[rows][None], values[t][None], reference[t][rows][None], shape)
                slots = slots.index_add(0, rows, read[0].to(slots.dtype))  # autocast: read in bf16, sum in float32
        count = seen.sum(0).clamp_min(1).to(query.dtype)[:, None]
        return self.dropout(self.output_proj(slots / count)) + query


class DeformSelfAttention(nn.Module):
    """The query volume attends to itself (``num_bev_queue`` = 2, one level), on a plane or in 3-D."""

    def __init__(self, embed_dims: int, num_heads: int = 8, num_points: int = 8, space: str = "plane",
                 dropout: float = 0.1) -> None:
        super().__init__()
        if embed_dims % num_heads:
            raise ValueError(f"channels ({embed_dims}) must be divisible by heads ({num_heads})")
        if space not in ("plane", "3d"):
            raise ValueError(f"space must be 'plane' or '3d', got {space!r}")
        self.heads, self.points, self.space, self.queues = num_heads, num_points, space, 2
        self.dims = 2 if space == "plane" else 3
        self.sampling_offsets = nn.Linear(2 * embed_dims, self.queues * num_heads * num_points * self.dims)
        self.attention_weights = nn.Linear(2 * embed_dims, self.queues * num_heads * num_points)
        self.value_proj = nn.Linear(embed_dims, embed_dims)
        self.output_proj = nn.Linear(embed_dims, embed_dims)
        self.dropout = nn.Dropout(dropout)
        nn.init.zeros_(self.sampling_offsets.weight)
        with torch.no_grad():
            ring = _ring(num_heads, self.queues, num_points)
            if self.dims == 3:  # the 3-D release initialises the same way, with a zero z
                ring = torch.cat([ring, torch.zeros_like(ring[..., :1])], -1)
            self.sampling_offsets.bias.copy_(ring.reshape(-1))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        _xavier(self.value_proj)
        _xavier(self.output_proj)

    def cells(self, volume: tuple[int, int, int]) -> tuple[int, ...]:
        """The cells the values live on: the plane the flat queries fold to, or the volume."""
        return plane_shape(volume[0] * volume[1] * volume[2]) if self.space == "plane" else volume

    def forward(self, query: Tensor, pos: Tensor, volume: tuple[int, int, int]) -> Tensor:
        """``query`` (B, N, C) over the (X, Y, Z) ``volume`` in flat order, ``pos`` (N, C) -> (B, N, C)."""
        b, n, c = query.shape
        cells = self.cells(volume)
        q = torch.cat([query, query + pos], -1)
        value = self.value_proj(query).view(b, n, self.heads, -1)
        offsets = self.sampling_offsets(q).view(b, n, self.heads, self.queues, self.points, self.dims)
        weights = self.attention_weights(q).view(b, n, self.heads, self.queues, self.points).softmax(-1)
        norm = query.new_tensor([cells[1], cells[0], *cells[2:]])  # (w, h[, z])
        locations = reference(cells, query.device, query.dtype)[None, :, None, None, None, :] + offsets / norm
        reads = [deformable_read(value, cells, locations[:, :, :, i], weights[:, :, :, i]) for i in range(self.queues)]
        return self.dropout(self.output_proj((reads[0] + reads[1]) / 2)) + query


def plane_shape(n: int) -> tuple[int, int]:
    """The (rows, columns) the ``plane`` space folds ``n`` queries to: the most square factors (262 144 -> 512 x
    512, VoxFormer's)."""
    rows = max(d for d in range(1, math.isqrt(n) + 1) if n % d == 0)
    return rows, n // rows


def reference(cells: tuple[int, ...], device: torch.device, dtype: torch.dtype) -> Tensor:
    """(N, d) reference locations of the cells in their flat order: ((column + 0.5) / w, (row + 0.5) / h) on a plane
    (h, w); ((j + 0.5) / w, (i + 0.5) / h, (k + 0.5) / z) in a volume (h, w, z)."""
    axes = [(torch.arange(s, device=device, dtype=dtype) + 0.5) / s for s in cells]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).view(-1, len(cells))
    return torch.cat([grid[:, 1:2], grid[:, 0:1], grid[:, 2:]], 1)


__all__ = ["DeformCrossAttention", "DeformSelfAttention", "MSDeformableAttention3D", "deformable_read", "plane_shape",
           "reference"]
