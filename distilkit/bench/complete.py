"""``distilkit bench complete``: ``distilkit complete`` on an HDL-64E-sized scan, with and without refinement."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.bench.base import Case, register
from distilkit.bench.fixtures import lidiff_models, street


@register("complete")
def complete_cases(device: torch.device, quick: bool) -> list[Case]:
    """``distilkit complete`` on a scan the size of an HDL-64E sweep (125,000 points; 20,000 with --quick): LiDAR-frame
    preparation and farthest-point sampling to LiDiff's 18,000 scan points (1,024 quick), 8 DPM-free DDIM steps at
    guidance 3.5 into 10x the points, post-processing; 'fast' without refinement, 'naive' with the 6x refinement
    network on top (the columns compare the two: the refinement's time and memory)."""
    n, scan = (20_000, 1024) if quick else (125_000, 18_000)
    model, refiner = lidiff_models(device, scan)
    raw = street(n, 1, torch.device("cpu")).numpy()

    def run(refine: bool) -> Tensor:
        with torch.no_grad():
            scene, _, _ = model.complete_scan(raw, scan_points=scan, steps=8, guidance=3.5)
            if refine:
                scene = refiner.refine_cloud(scene)
        return torch.tensor(float(len(scene)))

    return [Case("complete vs complete + refine", f"{n:,}-pt scan → {10 * scan:,} → ×6 pts",
                 lambda: run(False), lambda: run(True), [], same_value=False)]

