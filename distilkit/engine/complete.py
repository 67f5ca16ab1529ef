"""``distilkit complete``: a trained point-diffusion model completes a user's scan into a dense scene.

The scan is prepared as LiDiff prepares its input (seed_code.md §3.1): points with 3.5 m < range < 50 m and
z > -4 m, tiled and farthest-point-sampled to the number of scan points the model was trained with (read from the
run's ``recipe.resolved.yaml``; ``--scan-points`` overrides). The completion keeps LiDiff's post-processing: range
< 50 m and z between mean - 2 std of the input's heights and the input's highest point. A real scan carries no
labels, so moving objects are not removed here (LiDiff's training data has none).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from distilkit.data.pointfiles import read_points, write_points
from distilkit.data.scenes import farthest_point_sample, scan_crop, tile_to
from distilkit.errors import DataError, DistilkitError


@dataclass
class Completion:
    out: Path
    scan_points: int
    input_points: int
    output_points: int
    steps: int
    seconds: float


def _model(source: Path) -> tuple[Any, dict[str, Any]]:
    """The run's model (best checkpoint, else last) and the data parameters it was trained with."""
    from distilkit.engine.runs import checkpoint_path, load_run, run_config

    path = checkpoint_path(source, "any")
    model = load_run(path)
    if not callable(getattr(model, "sample", None)):
        raise DistilkitError(f"adapter {type(model).__name__} cannot complete a scan: it offers no "
                             "sample(condition, steps)")
    return model, (run_config(path).get("data") or {}).get("params") or {}


def prepare_scan(points: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """LiDiff's input: range and height crops, tiled, farthest-point-sampled to ``count`` points."""
    kept = scan_crop(points, 3.5, 50.0, -4.0)
    if len(kept) == 0:
        raise DataError("the scan has no point with 3.5 m < range < 50 m and z > -4 m")
    kept = tile_to(kept, count)
    start = int(np.random.default_rng(seed).integers(len(kept)))
    return kept[farthest_point_sample(kept, count, start)]


def postprocess(scene: np.ndarray, scan: np.ndarray) -> np.ndarray:
    """LiDiff's post-processing: range < 50 m, z in (mean - 2 std, max) of the input's heights."""
    z = scan[:, 2]
    keep = (np.linalg.norm(scene[:, :2], axis=1) < 50.0) & (scene[:, 2] > z.mean() - 2 * z.std()) & (scene[:, 2] < z.max())
    return scene[keep]


def complete(checkpoint: str | Path, scan: str | Path, out: str | Path, steps: int | None = None,
             guidance: float | None = None, scan_points: int | None = None, seed: int = 0,
             device: str = "cpu", status: Any = None) -> Completion:
    """Complete ``scan`` with the model in ``checkpoint`` (a checkpoint file or a stage's run folder); write ``out``."""
    t0 = time.perf_counter()
    model, data_params = _model(Path(checkpoint).expanduser())
    count = scan_points or int(data_params.get("scan_points", 18_000))
    raw = read_points(scan)
    if status:
        status(f"preparing {len(raw):,} points → {count:,}")
    prepared = prepare_scan(raw, count, seed)
    dev = torch.device(device)
    model = model.to(dev)
    n_steps = steps or int(model.params.sample_steps)
    if status:
        status(f"sampling in {n_steps} steps")
    with torch.no_grad():
        cond = torch.from_numpy(prepared)[None].to(dev)
        scene = model.sample(cond, steps=n_steps, guidance=guidance, generator=torch.Generator(device=dev).manual_seed(seed))
    result = postprocess(scene[0].cpu().numpy(), prepared)
    path = write_points(out, result)
    return Completion(path, count, len(raw), len(result), n_steps, time.perf_counter() - t0)


__all__ = ["Completion", "complete", "postprocess", "prepare_scan"]
