"""``distilkit bench networks``: each family's network at ``size: tiny`` and ``size: paper`` — parameters, one
training step's forward + backward time and peak memory — on one sample at the papers' sizes: a HDL-64E-sized scan
(64 beams x 2,048 azimuth steps of the synthetic streets) on the 256 x 256 x 32 grid for SCPNet and JS3C-Net, an
18,000-point scan completed to 180,000 points for LiDiff and its refiner, a 370 x 1220 image and the 256 x 256 x 32
grid for VoxFormer (queries at the ground truth's occupied half-resolution voxels, as many as a good proposal).
``--quick`` takes a quarter of each (the 128 x 128 x 16 grid at 0.4 m, 4,500 / 45,000 points, a 184 x 610 image).

Every model is built through the adapter registry from a recipe-like case (adapter, parameters, dataset, data
parameters: :func:`distilkit.bench.fixtures.network_cases`, shared with ``distilkit bench step``), with random
weights (the cost does not depend on them); the step's loss is the mean of every floating-point tap that carries a
gradient, so the backward reaches every parameter the taps depend on.
The first step is the warm-up and measures memory: the peak of the bytes PyTorch holds (the profiler's allocation
events on the CPU, ``max_memory_allocated`` on CUDA, as ``validate``'s estimate counts them), parameters and their
gradients included; the second is timed.
"""

from __future__ import annotations

import time
from typing import Any

import torch
from torch import Tensor

from distilkit.bench.base import Case, register
from distilkit.bench.fixtures import NetworkCase, build, network_cases, tap_loss as _loss


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
