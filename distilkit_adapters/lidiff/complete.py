"""LiDiff's conventions for completing a user's scan (seed_code.md §3.1): the input is cropped to 3.5 m < range <
50 m and z > -4 m, tiled and farthest-point-sampled to the number of scan points the model was trained with; the
completion keeps points within 50 m (3-D range) whose height lies between mean - 2 std of the input's heights and the input's
highest point. A real scan carries no labels, so moving objects are not removed here (LiDiff's training data has
none)."""

from __future__ import annotations

import numpy as np
from torch import Tensor

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


def keep_mask(scene: Tensor, scan: Tensor, max_range: float = 50.0) -> Tensor:
    """LiDiff's post-processing of a completion (M, 3) given its input scan (N, 3), as a mask: 3-D range <
    ``max_range``, z in (mean - 2 std, max) of the input's heights (population std, as numpy's)."""
    z = scan[:, 2]
    low, high = z.mean() - 2 * z.std(correction=0), z.max()
    return (scene.norm(dim=1) < max_range) & (scene[:, 2] > low) & (scene[:, 2] < high)


__all__ = ["DEFAULT_SCAN_POINTS", "keep_mask", "prepare_scan"]
