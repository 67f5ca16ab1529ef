"""``distilkit complete``: a trained scene-completion model completes a user's scan into a dense scene.

The model is rebuilt from its run (:func:`~distilkit.engine.assemble.runs.load_run`); its adapter offers the
:class:`ScanCompleter` capability, which prepares the scan and post-processes the result by its own conventions
(LiDiff's: :mod:`distilkit_adapters.lidiff.complete`). The number of scan points defaults to what the run was
trained with (its ``recipe.resolved.yaml``); ``--scan-points`` overrides it. ``--refine RUN`` passes the completion
through a refinement model's :class:`PointRefiner` capability (LiDiff's refinement network, ``lidiff-refine``), as
LiDiff's pipeline does after its post-processing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from distilkit.data.pointfiles import read_points, write_points
from distilkit.errors import DistilkitError


@runtime_checkable
class ScanCompleter(Protocol):
    def complete_scan(self, points: np.ndarray, *, scan_points: int | None = None, steps: int | None = None,
                      guidance: float | None = None, seed: int = 0) -> tuple[np.ndarray, int, int]:
        """(completed scene (M, 3), scan points it was sampled to, sampler steps) from a raw (N, 3) scan."""


@runtime_checkable
class PointRefiner(Protocol):
    def refine_cloud(self, points: np.ndarray) -> np.ndarray:
        """A refined scene from a completed one ((M, 3) -> (M', 3))."""


@dataclass
class Completion:
    out: Path
    scan_points: int
    input_points: int
    output_points: int
    steps: int
    seconds: float
    refined: bool = False


def _model(source: Path, capability: type, what: str) -> tuple[Any, dict[str, Any]]:
    """The run's model (best checkpoint, else last) and the data parameters it was trained with."""
    from distilkit.engine.assemble.runs import checkpoint_path, load_run, run_config

    path = checkpoint_path(source, "any")
    model = load_run(path)
    if not isinstance(model, capability):
        raise DistilkitError(f"{source}: adapter {type(model).__name__} cannot {what}")
    return model, (run_config(path).get("data") or {}).get("params") or {}


def complete(checkpoint: str | Path, scan: str | Path, out: str | Path, steps: int | None = None,
             guidance: float | None = None, scan_points: int | None = None, seed: int = 0,
             device: str = "cpu", status: Any = None, refine: str | Path | None = None) -> Completion:
    """Complete ``scan`` with the model in ``checkpoint`` (a checkpoint file or a stage's run folder), refine it with
    the model of ``refine`` if given; write ``out``."""
    import math

    for name, value in (("--steps", steps), ("--scan-points", scan_points)):
        if value is not None and value < 1:
            raise DistilkitError(f"{name} {value}: must be at least 1 (leave it out for the model's own)")
    if guidance is not None and not (math.isfinite(guidance) and guidance >= 0):
        raise DistilkitError(f"--guidance {guidance}: must be a finite number >= 0 (1: the conditional prediction "
                             "alone)")
    t0 = time.perf_counter()
    model, data_params = _model(Path(checkpoint).expanduser(), ScanCompleter,
                                "complete a scan: it offers no complete_scan(points, ...)")
    refiner = None
    if refine is not None:
        refiner = _model(Path(refine).expanduser(), PointRefiner,
                         "refine a completion: it offers no refine_cloud(points)")[0].to(torch.device(device))
    model = model.to(torch.device(device))
    raw = read_points(scan)
    if status:
        status(f"completing {len(raw):,} scan points")
    with torch.no_grad():
        scene, count, n_steps = model.complete_scan(raw, scan_points=scan_points or data_params.get("scan_points"),
                                                    steps=steps, guidance=guidance, seed=seed)
        if refiner is not None:
            if status:
                status(f"refining {len(scene):,} completed points")
            scene = refiner.refine_cloud(scene)
    if len(scene) == 0:
        raise DistilkitError(f"{scan}: the completion of its {len(raw):,} points holds no point after the model's "
                             "post-processing (LiDiff's keeps heights within 2 std of the scan's mean and below its "
                             "highest point: a scan this small or flat leaves nothing); nothing written")
    path = write_points(out, scene)
    return Completion(path, count, len(raw), len(scene), n_steps, time.perf_counter() - t0, refiner is not None)


__all__ = ["Completion", "PointRefiner", "ScanCompleter", "complete"]
