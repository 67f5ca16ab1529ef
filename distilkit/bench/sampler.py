"""``distilkit bench sampler | guidance``: LiDiff's sampler at the distilled student's step count against the
teacher's, and with classifier-free guidance against without — the same denoiser, random weights (the time does not
depend on them)."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.bench.base import Case, register
from distilkit.bench.fixtures import lidiff_models, street


@register("sampler")
def sampler_cases(device: torch.device, quick: bool) -> list[Case]:
    """ScoreLiDAR's claim (Table 4): the distilled student samples in 8 steps what the LiDiff teacher samples in 50 —
    the same denoiser, timed side by side ('fast' = 8 steps, 'naive' = 50). The model is built through the adapter
    registry at recipes/scorelidar.yaml's size (weights random: the time does not depend on them)."""
    cases = []
    for scan in ((64,) if quick else (256, 1024)):
        model, _ = lidiff_models(device, scan)
        points = street(scan, 0, device)[None]

        def run(steps: int, model=model, points=points) -> Tensor:
            with torch.no_grad():
                return model.sample(points, steps=steps, generator=torch.Generator().manual_seed(0)).sum()

        cases.append(Case("sampler 8 vs 50 steps", f"{scan:,}-pt scan → {10 * scan:,} pts", lambda run=run: run(8),
                          lambda run=run: run(50), [], same_value=False))
    return cases


@register("guidance")
def guidance_cases(device: torch.device, quick: bool) -> list[Case]:
    """The cost of classifier-free guidance (LiDiff 6.0, ScoreLiDAR 3.5): its second, unconditional network call per
    step, 8 steps with guidance 1 ('fast': one call) and 3.5 ('naive': two calls), per scene."""
    cases = []
    for scan in ((64,) if quick else (256, 1024)):
        model, _ = lidiff_models(device, scan)
        points = street(scan, 0, device)[None]

        def run(w: float, model=model, points=points) -> Tensor:
            with torch.no_grad():
                return model.sample(points, steps=8, guidance=w, generator=torch.Generator().manual_seed(0)).sum()

        cases.append(Case("guidance 1 vs 3.5, 8 steps", f"{scan:,}-pt scan → {10 * scan:,} pts",
                          lambda run=run: run(1.0), lambda run=run: run(3.5), [], same_value=False))
    return cases

