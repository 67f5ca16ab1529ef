"""A LiDiff-style conditional point denoiser in pure PyTorch (CPU-friendly), and its diffusion process.

LiDiff (Nunes et al., CVPR 2024; seed_code.md §3.1-3.2):

* forward process with *local* offset noise: x_t = x_0 + sqrt(1 - abar_t) eps, betas linspace(3.5e-5, 7e-3, 1000);
* sampling starts from the scan duplicated K times plus N(0, I) and denoises the offset x_t - x_init;
* the denoiser is conditioned on the scan through nearest-neighbour features of a scan encoder and on t through a
  sinusoidal embedding, both entering by multiplicative modulation (x * w, no shift); its head is
  Linear(C -> 20), LeakyReLU(0.1), Linear(20 -> 3).

The sparse MinkUNet of the paper is replaced by point-wise MLP blocks on each noisy point, its offset to the nearest
scan points and their encoder features (no MinkowskiEngine, no KeOps: it runs on the CPU).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from distilkit.geometry.nearest import knn_indices


def lidiff_alphas_cumprod(steps: int = 1000, beta_start: float = 3.5e-5, beta_end: float = 0.007) -> Tensor:
    """abar_t for t = 0..steps-1 (float64), LiDiff's linear betas."""
    betas = torch.linspace(beta_start, beta_end, steps, dtype=torch.float64)
    return torch.cumprod(1.0 - betas, dim=0)


def timestep_embedding(t: Tensor, dim: int) -> Tensor:
    """Sinusoidal embedding (B, dim) of integer timesteps (B,)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10_000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=1)
    return torch.nn.functional.pad(emb, (0, dim - emb.shape[1]))


def _mlp(*widths: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(widths[:-1], widths[1:]):
        layers += [nn.Linear(a, b), nn.LeakyReLU(0.1)]
    return nn.Sequential(*layers[:-1])


def _gather(values: Tensor, idx: Tensor) -> Tensor:
    """values (B, N, C), idx (B, M, k) -> (B, M, k, C)."""
    b, m, k = idx.shape
    flat = idx.reshape(b, m * k, 1).expand(-1, -1, values.shape[-1])
    return values.gather(1, flat).view(b, m, k, values.shape[-1])


class ScanEncoder(nn.Module):
    """Per-point features of the scan: an MLP of each point and the max over its ``k`` nearest scan neighbours'
    offsets (an EdgeConv-like local descriptor)."""

    def __init__(self, channels: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.point = _mlp(3, channels, channels)
        self.edge = _mlp(channels + 3, channels, channels)

    def forward(self, scan: Tensor) -> Tensor:
        idx = torch.stack([knn_indices(s, s, self.k) for s in scan])  # (B, N, k)
        feats = self.point(scan)
        rel = _gather(scan, idx) - scan[:, :, None]
        return self.edge(torch.cat([_gather(feats, idx), rel], dim=-1)).amax(dim=2)


class PointDenoiser(nn.Module):
    """eps_hat(x_t, t, scan): (B, M, 3) noisy points -> (B, M, 3) predicted noise."""

    def __init__(self, channels: int = 64, blocks: int = 3, k_scan: int = 8, k_cond: int = 4, t_dim: int = 32) -> None:
        super().__init__()
        self.k_cond, self.t_dim = k_cond, t_dim
        self.encoder = ScanEncoder(channels, k_scan)
        self.cond = _mlp(channels + 3, channels, channels)
        self.time = _mlp(t_dim, channels, channels)
        self.inp = _mlp(3, channels, channels)
        self.mod = nn.ModuleList(_mlp(2 * channels, channels, channels) for _ in range(blocks))
        self.body = nn.ModuleList(_mlp(channels, channels, channels) for _ in range(blocks))
        self.head = nn.Sequential(nn.Linear(channels, 20), nn.LeakyReLU(0.1), nn.Linear(20, 3))

    def forward(self, x_t: Tensor, t: Tensor, scan: Tensor, enc: Tensor | None = None) -> Tensor:
        """``enc``: ``self.encoder(scan)`` when the caller has it already (a sampler encodes its scan once)."""
        enc = self.encoder(scan) if enc is None else enc
        idx = torch.stack([knn_indices(x, s, self.k_cond) for x, s in zip(x_t, scan)])  # (B, M, k)
        rel = x_t[:, :, None] - _gather(scan, idx)
        cond = self.cond(torch.cat([_gather(enc, idx), rel], dim=-1)).amax(dim=2)  # (B, M, C)
        temb = self.time(timestep_embedding(t, self.t_dim))[:, None].expand_as(cond)
        h = self.inp(rel[:, :, 0])  # offset to the nearest scan point
        for mod, body in zip(self.mod, self.body):
            h = h + body(h * mod(torch.cat([cond, temb], dim=-1)))  # multiplicative modulation
        return self.head(h)


__all__ = ["PointDenoiser", "lidiff_alphas_cumprod", "timestep_embedding"]
