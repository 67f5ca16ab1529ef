"""``distilkit bench networks``: each family's network at ``size: tiny`` and ``size: paper`` — parameters, one
training step's forward + backward time and peak memory — on one sample at the papers' sizes: a HDL-64E-sized scan
(64 beams x 2,048 azimuth steps of the synthetic streets) on the 256 x 256 x 32 grid for SCPNet and JS3C-Net, an
18,000-point scan completed to 180,000 points for LiDiff and its refiner, a 370 x 1220 image and the 256 x 256 x 32
grid for VoxFormer (queries at the ground truth's occupied half-resolution voxels, as many as a good proposal).
``--quick`` takes a quarter of each (the 128 x 128 x 16 grid at 0.4 m, 4,500 / 45,000 points, a 184 x 610 image).

Every model is built through the adapter registry from a recipe-like case (adapter, parameters, dataset, data
parameters: the cases below), with random weights (the cost does not depend on them); the step's loss is the mean
of every floating-point tap that carries a gradient, so the backward reaches every parameter the taps depend on.
The first step is the warm-up and measures memory: the peak of the bytes PyTorch holds (the profiler's allocation
events on the CPU, ``max_memory_allocated`` on CUDA, as ``validate``'s estimate counts them), parameters and their
gradients included; the second is timed.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from distilkit.bench.base import Case, register


@dataclass
class NetworkCase:
    family: str
    adapter: str
    dataset: str
    size: str  # "tiny" | "paper"
    data: dict[str, Any]
    params: dict[str, Any] = field(default_factory=dict)
    what: str = ""


def network_cases(quick: bool) -> list[NetworkCase]:
    """The families at both sizes on the papers' data sizes (quick: a quarter of them)."""
    scale = 2 if quick else 1
    lidar = {"scale": scale, "beams": 64, "azimuth_steps": 1024 if quick else 2048, "input_frames": 1,
             "gt_frames": 0 if quick else 4, "num_train": 1, "num_val": 1, "num_test": 1}
    camera = {**lidar, "camera": {"height": 184 if quick else 370, "width": 610 if quick else 1220, "previous": []}}
    scan = 4500 if quick else 18000
    scenes = {"scan_points": scan, "scene_points": 10 * scan, "num_train": 1, "num_val": 1, "num_test": 1,
              "azimuth_steps": 1024 if quick else 2048}
    grid = "128x128x16" if quick else "256x256x32"
    lidar_what = f"64-beam scan ({lidar['azimuth_steps']:,} steps), {grid}"
    cases = []
    for size in ("tiny", "paper"):
        cases += [
            NetworkCase("SCPNet", "scpnet", "synthetic-lidar", size, lidar, {"size": size}, lidar_what),
            NetworkCase("JS3C-Net", "js3cnet", "synthetic-lidar", size, lidar, {"size": size}, lidar_what),
            NetworkCase("LiDiff", "lidiff", "synthetic-scenes", size, scenes, {"size": size},
                        f"{scan:,} -> {10 * scan:,} points"),
            NetworkCase("LiDiff refine", "lidiff-refine", "synthetic-scenes", size, scenes, {"size": size},
                        f"{10 * scan:,} points"),
            NetworkCase("VoxFormer", "voxformer", "synthetic-lidar", size, camera,
                        {"size": size, "geometry": "ground-truth"},
                        f"{camera['camera']['height']}x{camera['camera']['width']} image, {grid}"),
            NetworkCase("Dean-Labeler", "dean-labeler", "synthetic-lidar", size, lidar, {"size": size},
                        f"complete geometry, {grid}"),
        ]
    return cases


def _batch(case: NetworkCase, device: torch.device) -> tuple[Any, Any]:
    from distilkit.registry import DATASETS

    entry = DATASETS.entry(case.dataset)
    params = entry.meta["params"](**case.data)
    info = entry.meta["info"](params)
    sample = entry.obj(params, "train")[0]
    return entry.meta["collate"]([sample]).to(device), info


def _loss(taps: dict[str, Any]) -> Tensor:
    """The mean of every floating-point tap with a gradient (tensors, the ``feats`` of sparse taps, the ``points`` of
    point clouds)."""
    terms = []
    for value in taps.values():
        value = getattr(value, "feats", getattr(value, "points", value))
        if isinstance(value, Tensor) and value.is_floating_point() and value.requires_grad:
            terms.append(value.float().mean())
    return torch.stack(terms).sum()


def build(case: NetworkCase, device: torch.device) -> tuple[Any, Any]:
    """(model in training mode on ``device``, one collated sample)."""
    from distilkit.registry import ADAPTERS

    batch, info = _batch(case, device)
    cls = ADAPTERS.get(case.adapter)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = cls(cls.Params(**case.params), info).to(device).train()
    return model, batch


@register("networks")
def networks_cases(device: torch.device, quick: bool) -> list[Case]:
    """``distilkit bench`` cases: one training step of each network (no naive form: the table's figure is the
    network's own cost)."""

    out = []
    for case in network_cases(quick):
        model, batch = build(case, device)
        n = sum(p.numel() for p in model.parameters())

        def step(model: Any = model, batch: Any = batch) -> Tensor:
            model.zero_grad(set_to_none=True)
            return _loss(model(batch))

        out.append(Case(f"{case.family} {case.size}", f"{n / 1e6:.2f} M params; {case.what}", step, None, [],
                        measure=lambda step=step, model=model: measure(step, model, device)))
    return out


def measure(step: Any, model: Any, device: torch.device) -> tuple[float, int, float]:
    """(milliseconds of the second step, peak bytes of the first — parameters and gradients included —, loss)."""
    from distilkit.engine.memory.estimate import tensor_bytes, peak_of_step

    weights = tensor_bytes([*model.parameters(), *model.buffers()])
    peak = peak_of_step(lambda: step().backward(), device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    loss = step()
    loss.backward()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return (time.perf_counter() - t0) * 1000, weights + peak, float(loss.detach())


__all__ = ["NetworkCase", "build", "network_cases", "networks_cases"]
