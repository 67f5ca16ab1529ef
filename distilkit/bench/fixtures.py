"""Inputs that several benchmarks build the same way: a LiDAR-like street of points and recipes/scorelidar.yaml's
LiDiff models. Not a benchmark: no case is registered here."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


def street(m: int, seed: int, device: torch.device) -> Tensor:
    """A LiDAR-like scene of ``m`` points: a ground plane, walls and poles within 50 m (metres)."""
    g = torch.Generator().manual_seed(seed)
    part = m // 3
    ground = torch.cat([torch.rand(part, 2, generator=g) * 100 - 50, torch.randn(part, 1, generator=g) * 0.02 - 1.7], 1)
    wall = torch.cat([torch.rand(part, 1, generator=g) * 100 - 50, 8 + torch.randn(part, 1, generator=g) * 0.05,
                      torch.rand(part, 1, generator=g) * 4 - 1.7], 1)
    rest = m - 2 * part
    centres = (torch.rand(rest // 50 + 1, 2, generator=g) * 80 - 40).repeat_interleave(50, 0)[:rest]
    poles = torch.cat([centres + torch.randn(rest, 2, generator=g) * 0.1, torch.rand(rest, 1, generator=g) * 5 - 1.7], 1)
    return torch.cat([ground, wall, poles]).to(device)


def lidiff_models(device: torch.device, scan: int) -> tuple[Any, Any]:
    """recipes/scorelidar.yaml's LiDiff denoiser and refiner, built through the adapter registry (random weights: the
    time does not depend on them)."""
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info
    from distilkit.registry import ADAPTERS

    info = scenes_info(SceneParams(scan_points=scan, scene_points=10 * scan))
    with torch.random.fork_rng(devices=[]):
        lidiff, refine = ADAPTERS.get("lidiff"), ADAPTERS.get("lidiff-refine")
        model = lidiff(lidiff.Params(channels=32, blocks=2, duplicate=10, sample_steps=8), info).to(device).eval()
        refiner = refine(refine.Params(channels=32), info).to(device).eval()
    return model, refiner

