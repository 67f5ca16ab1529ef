"""LiDiff's conventions for completing a user's scan (seed_code.md §3.1): the input is cropped to 3.5 m < range <
50 m and z > -4 m, tiled and farthest-point-sampled to the number of scan points the model was trained with; the
completion keeps points within 50 m whose height lies between mean - 2 std of the input's heights and the input's
highest point. A real scan carries no labels, so moving objects are not removed here (LiDiff's training data has
none)."""

from __future__ import annotations

import numpy as np

from distilkit.data.scenes import farthest_point_sample, scan_crop, tile_to
from distilkit.errors import DataError

DEFAULT_SCAN_POINTS = 18_000  # LiDiff's


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


__all__ = ["DEFAULT_SCAN_POINTS", "postprocess", "prepare_scan"]
