"""Voxel queries that read image features: reference points projected into every frame's camera, and deformable
cross-attention around them (Zhu et al. ICLR 2021, as VoxFormer's spatial cross-attention uses it).

Each query predicts, per head, ``points`` sampling offsets (in feature-map pixels) around its reference point's
projection and one attention weight per frame and point; the values are read with ``grid_sample`` (bilinear, zero
outside the image) and summed with the weights, then averaged over the frames in which the reference point is seen
(BEVFormer's ``bev_mask``). A query seen in no frame is left as it was.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

DEPTH_EPS = 1e-5  # VoxFormer's: a reference point must lie in front of the camera


def project(points: Tensor, intrinsics: Tensor, to_camera: Tensor, size: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Pixel coordinates (N, T, 2) of LiDAR-frame points (N, 3) in T cameras (``intrinsics`` (N, T, 3, 3) and
    ``to_camera`` (N, T, 4, 4), each point's own sample's) and whether each is seen (in front, inside ``size``)."""
    homogeneous = torch.cat([points, torch.ones_like(points[:, :1])], 1)  # (N, 4)
    cam = torch.einsum("ntij,nj->nti", to_camera[..., :3, :], homogeneous)  # (N, T, 3)
    z = cam[..., 2:3]
    pix = torch.einsum("ntij,ntj->nti", intrinsics, cam)[..., :2] / z.clamp_min(DEPTH_EPS)
    h, w = size
    seen = (z[..., 0] > DEPTH_EPS) & (pix[..., 0] >= 0) & (pix[..., 0] < w) & (pix[..., 1] >= 0) & (pix[..., 1] < h)
    return pix, seen


class DeformableCrossAttention(nn.Module):
    """One deformable cross-attention layer over T frames' feature maps, with a residual, layer norms and an MLP."""

    def __init__(self, channels: int, heads: int, points: int, frames: int) -> None:
        super().__init__()
        if channels % heads:
            raise ValueError(f"channels ({channels}) must be divisible by heads ({heads})")
        self.heads, self.points, self.frames = heads, points, frames
        self.offsets = nn.Linear(channels, heads * frames * points * 2)
        self.weights = nn.Linear(channels, heads * frames * points)
        self.value = nn.Linear(channels, channels)
        self.out = nn.Linear(channels, channels)
        self.norm1 = nn.LayerNorm(channels)
        self.mlp = nn.Sequential(nn.Linear(channels, 2 * channels), nn.ReLU(), nn.Linear(2 * channels, channels))
        self.norm2 = nn.LayerNorm(channels)
        nn.init.zeros_(self.offsets.weight)  # start by reading each reference point's own pixel, then around it
        with torch.no_grad():
            angle = torch.arange(heads * points, dtype=torch.float32) * (2 * torch.pi / max(heads * points, 1))
            ring = torch.stack([angle.cos(), angle.sin()], -1).view(heads, 1, points, 2)
            self.offsets.bias.copy_(ring.expand(heads, frames, points, 2).reshape(-1))

    def forward(self, query: Tensor, pos: Tensor, batch_index: Tensor, pixels: Tensor, seen: Tensor,
                features: Tensor, image_size: tuple[int, int]) -> Tensor:
        """``query``/``pos`` (N, C) of the proposed voxels of all samples, ``batch_index`` (N,), their projections
        ``pixels`` (N, T, 2) and ``seen`` (N, T); ``features`` (B, T, C, h, w) of images of ``image_size`` (H, W).
        Returns the updated queries (N, C)."""
        n, c = query.shape
        hd, t, p = self.heads, self.frames, self.points
        b, _, _, fh, fw = features.shape
        q = query + pos
        scale = features.new_tensor([features.shape[-1] / image_size[1], features.shape[-2] / image_size[0]])
        where = pixels[:, None, :, None, :] * scale + self.offsets(q).view(n, hd, t, p, 2)  # feature-map pixels
        grid = where / where.new_tensor([fw, fh]) * 2 - 1  # grid_sample's coordinates (align_corners=False)
        attn = self.weights(q).view(n, hd, t, p).softmax(-1)  # per frame, over its points
        values = self.value(features.permute(0, 1, 3, 4, 2)).permute(0, 1, 4, 2, 3)  # (B, T, C, h, w)
        values = values.reshape(b, t, hd, c // hd, fh, fw)
        sampled = query.new_zeros(n, hd, t, c // hd)
        for i in range(b):  # samples hold different numbers of queries
            rows = torch.nonzero(batch_index == i).squeeze(1)
            if rows.numel() == 0:
                continue
            g = grid[rows].permute(1, 2, 0, 3, 4).reshape(hd * t, rows.numel(), p, 2)
            v = values[i].permute(1, 0, 2, 3, 4).reshape(hd * t, c // hd, fh, fw)
            s = F.grid_sample(v, g, mode="bilinear", padding_mode="zeros", align_corners=False)  # (hd*t, C/hd, n_i, p)
            s = s.view(hd, t, c // hd, rows.numel(), p).permute(3, 0, 1, 4, 2)  # (n_i, hd, t, p, C/hd)
            sampled[rows] = (s * attn[rows, ..., None]).sum(3)
        mask = seen[:, None, :, None].to(sampled.dtype)
        count = seen.sum(1).clamp_min(1).to(sampled.dtype)[:, None, None]
        read = (sampled * mask).sum(2) / count  # (N, hd, C/hd): the frames that see the point, averaged
        update = self.out(read.reshape(n, c)) * seen.any(1, keepdim=True).to(query.dtype)
        x = self.norm1(query + update)
        return self.norm2(x + self.mlp(x))


__all__ = ["DEPTH_EPS", "DeformableCrossAttention", "project"]
