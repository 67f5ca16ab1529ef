"""Point-cloud scene completion data as LiDiff trains on it (seed_code.md §3.1), from the synthetic streets.

One sample, around the current frame of a drive along the street (SemanticKITTI sensor frame):

* ``scan`` (N, 3): the current scan's static points with 3.5 m < range < ``max_range`` (3-D range, as LiDiff's
  ``SemanticKITTITemporal``) and z > -4 m, tiled and farthest-point-sampled to ``scan_points`` (LiDiff: 18,000);
* ``scene`` (M, 3): the map — the static points of every scan of the drive (``frames`` of them, the current one in
  the middle; each scan's points within 3.5 m of its sensor dropped, as ``map_from_scans.py`` does), one original
  point per ``gt_voxel`` voxel of the world frame (the first in scan order: MinkowskiEngine's ``sparse_quantize``
  with ``return_index``, not a mean) — within ``max_range`` of the current pose (3-D) and z > -4 m, kept where a
  ``viewpoint_voxel`` cell holds a point of the cropped scan before sampling (LiDiff's 10 m "viewpoint" crop: an
  Open3D ``VoxelGrid`` anchored at the scan's minimum bound less half a cell), randomly permuted and tiled to
  ``scene_points`` (LiDiff: 180,000 = 10 x 18,000);
* ``scene_eval`` (E, 3): the ground truth LiDiff *evaluates* against (data_metrics.md §3.2): the same map points
  within ``max_range`` of the current pose (3-D distance) with ``min_z`` < z < 4.4 m, kept in the 10 m viewpoint
  cells of the raw current scan (every point within ``max_range``, moving ones included; the grid anchored at that
  scan's minimum bound), neither permuted nor tiled (its length varies).

Moving objects (raw ids >= 252) and unlabelled points are left out of both, as LiDiff's maps do.
The batch holds padded clouds with lengths (PyTorch3D's convention): inputs ``scan``/``scan_lengths``,
targets ``scene``/``scene_lengths`` and ``scene_eval``/``scene_eval_lengths``, meta ``scene_id`` (stable per split and index, for per-scene caches).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from distilkit.data.batch import Batch
from distilkit.data.facts import SCENE_FIELDS, scenes_info
from distilkit.data.params import SceneParams
from distilkit.data.raycast import ray_directions
from distilkit.data.cache import cached_samples
from distilkit.data.street_layout import EGO_LANE_Y, SENSOR_HEIGHT, make_scene
from distilkit.data.synthetic import cast_scan

SCENES_VERSION = 3  # 2: the untiled evaluation ground truth ``scene_eval``; 3: LiDiff's crops (3-D range, viewpoint
# grid at the scan's minimum bound, one original point per map voxel, 3.5 m around each sensor dropped)
EVAL_MAX_Z = 4.4  # LiDiff's evaluation keeps -4 < z < 4.4


def farthest_point_sample(points: np.ndarray, count: int, start: int = 0) -> np.ndarray:
    """Indices of ``count`` points chosen by farthest-point sampling from ``points[start]`` (O(count * n),
    numpy on per-axis arrays with preallocated buffers: single-threaded, which beats a thread pool here)."""
    n = len(points)
    if count > n:
        raise ValueError(f"farthest-point sampling of {count} points from {n}")
    x, y, z = (np.ascontiguousarray(points[:, a], dtype=np.float32) for a in range(3))
    chosen = np.empty(count, dtype=np.int64)
    dist = np.full(n, np.inf, dtype=np.float32)
    d, tmp = np.empty(n, np.float32), np.empty(n, np.float32)
    i = start
    for j in range(count):
        chosen[j] = i
        np.subtract(x, x[i], out=d)
        np.multiply(d, d, out=d)
        np.subtract(y, y[i], out=tmp)
        np.multiply(tmp, tmp, out=tmp)
        d += tmp
        np.subtract(z, z[i], out=tmp)
        np.multiply(tmp, tmp, out=tmp)
        d += tmp
        np.minimum(dist, d, out=dist)
        i = int(dist.argmax())
    return chosen


def tile_to(points: np.ndarray, count: int) -> np.ndarray:
    """Repeat ``points`` until there are at least ``count`` of them (LiDiff tiles before sampling)."""
    if len(points) == 0:
        raise ValueError("cannot tile an empty point set")
    reps = -(-count // len(points))
    return np.tile(points, (reps, 1)) if reps > 1 else points


def scan_crop(xyz: np.ndarray, min_range: float, max_range: float, min_z: float) -> np.ndarray:
    """The points with ``min_range`` < 3-D range < ``max_range`` and z > ``min_z`` (LiDiff's crop: the Euclidean norm
    of the point, not its distance in the ground plane)."""
    r = np.linalg.norm(xyz, axis=1)
    return xyz[(r > min_range) & (r < max_range) & (xyz[:, 2] > min_z)]


def voxel_first(xyz: np.ndarray, voxel: float, shift: np.ndarray | None = None) -> np.ndarray:
    """One original point per occupied voxel of ``floor((xyz + shift) / voxel)``: the first one (LiDiff's maps, made
    with MinkowskiEngine's ``sparse_quantize(..., return_index=True)``, keep points, not means). ``shift`` moves the
    points into the frame whose grid is meant (the world frame of a map), without moving what is returned."""
    base = xyz.astype(np.float64) + (0.0 if shift is None else np.asarray(shift, np.float64))
    _, first = np.unique(np.floor(base / voxel).astype(np.int64), axis=0, return_index=True)
    return xyz[np.sort(first)]


def viewpoint_crop(scene: np.ndarray, scan: np.ndarray, voxel: float) -> np.ndarray:
    """The scene points inside the ``voxel``-sized cells that hold a scan point, the cells of an Open3D
    ``VoxelGrid.create_from_point_cloud(scan, voxel)``: anchored at the scan's minimum bound less half a cell
    (``check_if_included``)."""
    if len(scan) == 0:
        return scene[:0]
    origin = scan.astype(np.float64).min(axis=0) - voxel / 2

    def key(xyz: np.ndarray) -> np.ndarray:
        k = np.floor((xyz.astype(np.float64) - origin) / voxel).astype(np.int64) + 1_000_000
        return (k[:, 0] * 2_000_001 + k[:, 1]) * 2_000_001 + k[:, 2]

    return scene[np.isin(key(scene), key(scan))]


def make_scene_sample(seed: int, p: SceneParams) -> dict[str, np.ndarray]:
    """Generate one (scan, scene) pair; see the module docstring."""
    rng = np.random.default_rng(seed)
    cur = p.frames // 2
    x0 = rng.uniform(0, 20)
    scene = make_scene(rng, x0 - p.max_range - 10, x0 + p.ego_speed * p.frames + p.max_range + 10, p.ego_speed, x0,
                       p.frames)
    dirs = ray_directions(p.beams, p.azimuth_steps, p.fov_up, p.fov_down)
    ego = np.array([x0 + p.ego_speed * cur, EGO_LANE_Y, SENSOR_HEIGHT], np.float32)
    statics = []
    scan = raw = np.zeros((0, 3), np.float32)
    for j in range(p.frames):
        origin = np.array([x0 + p.ego_speed * j, EGO_LANE_Y, SENSOR_HEIGHT], np.float32)
        s = cast_scan(scene, origin, j, dirs, rng, p.max_range, p.range_noise)
        static = (s.label >= 1) & (s.label < 252)
        near = np.linalg.norm(s.xyz - origin[None, :], axis=1) <= p.min_range  # map_from_scans drops these
        xyz = s.xyz[static & ~near] - ego[None, :]  # the current sensor frame (the ego drives along +x, heading 0)
        statics.append(xyz)
        if j == cur:
            scan, raw = s.xyz[static] - ego[None, :], s.xyz - ego[None, :]
    cropped = scan_crop(scan, p.min_range, p.max_range, p.min_z)
    if len(cropped) == 0:
        raise ValueError(f"scene seed {seed}: the scan has no static point in range")
    partial = tile_to(cropped, p.scan_points)
    partial = partial[farthest_point_sample(partial, p.scan_points, int(rng.integers(len(partial))))]
    world = voxel_first(np.concatenate(statics), p.gt_voxel, ego)  # the map, one point per world-frame voxel
    full = scan_crop(world, 0.0, p.max_range, p.min_z)
    full = viewpoint_crop(full, cropped, p.viewpoint_voxel)  # the grid of the scan before sampling, as LiDiff's
    full = tile_to(full[rng.permutation(len(full))], p.scene_points)[: p.scene_points]
    return {"scan": partial.astype(np.float32), "scene": full.astype(np.float32),
            "scene_eval": evaluation_ground_truth(world, raw, p).astype(np.float32)}


def evaluation_ground_truth(world: np.ndarray, raw_scan: np.ndarray, p: SceneParams) -> np.ndarray:
    """LiDiff's per-scan evaluation ground truth (``get_ground_truth``): map points (here: the static points of the
    drive, one per ``gt_voxel``, as :func:`make_scene_sample` makes them) within ``max_range`` of the sensor (3-D),
    ``min_z`` < z < 4.4, inside the 10 m viewpoint cells of the raw scan's points within ``max_range``."""
    gt = world[(np.linalg.norm(world, axis=1) < p.max_range) & (world[:, 2] > p.min_z) & (world[:, 2] < EVAL_MAX_Z)]
    view = raw_scan[np.linalg.norm(raw_scan, axis=1) < p.max_range]
    return viewpoint_crop(gt, view, p.viewpoint_voxel)


def _stack_padded(samples: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Fixed-size arrays stacked; ``scene_eval`` zero-padded to the longest, with ``scene_eval_lengths``."""
    out = {k: np.stack([s[k] for s in samples]) for k in ("scan", "scene")}
    lengths = np.array([len(s["scene_eval"]) for s in samples], np.int64)
    padded = np.zeros((len(samples), int(lengths.max()), 3), np.float32)
    for i, s in enumerate(samples):
        padded[i, : lengths[i]] = s["scene_eval"]
    return {**out, "scene_eval": padded, "scene_eval_lengths": lengths}


def generate_scenes(p: SceneParams, split: str, count: int,
                    progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """``count`` samples of ``split`` stacked, from the on-disk cache when generated before (a corrupt cache
    entry is regenerated)."""
    return cached_samples("synthetic-scenes", SCENES_VERSION, p.model_dump(), split, count,
                          lambda seed: make_scene_sample(seed, p),
                          _stack_padded, progress)


class SceneDataset(torch.utils.data.Dataset):
    def __init__(self, arrays: dict[str, np.ndarray], split: str) -> None:
        self.a, self.split = arrays, split

    def __len__(self) -> int:
        return len(self.a["scan"])

    def __getitem__(self, i: int) -> dict[str, Any]:
        return {"scan": self.a["scan"][i], "scene": self.a["scene"][i],
                "scene_eval": self.a["scene_eval"][i, : int(self.a["scene_eval_lengths"][i])],
                "scene_id": f"{self.split}/{i}"}


def collate_scenes(samples: list[dict[str, Any]]) -> Batch:
    """Padded clouds with lengths: inputs ``scan``, targets ``scene`` and ``scene_eval``; meta ``scene_id``."""
    def pad(key: str) -> tuple[torch.Tensor, torch.Tensor]:
        clouds = [torch.from_numpy(np.asarray(s[key], np.float32)) for s in samples]
        m = max(len(c) for c in clouds)
        out = torch.zeros(len(clouds), m, 3)
        for b, c in enumerate(clouds):
            out[b, : len(c)] = c
        return out, torch.tensor([len(c) for c in clouds], dtype=torch.int64)

    scan, scan_len = pad("scan")
    scene, scene_len = pad("scene")
    targets = {"scene": scene, "scene_lengths": scene_len}
    if all("scene_eval" in s for s in samples):
        targets["scene_eval"], targets["scene_eval_lengths"] = pad("scene_eval")
    return Batch({"scan": scan, "scan_lengths": scan_len}, targets,
                 {"size": len(samples), "scene_id": [s.get("scene_id", "") for s in samples]})


def build_scenes(params: SceneParams, split: str, progress: Any = None) -> SceneDataset:
    count = {"train": params.num_train, "val": params.num_val, "test": params.num_test}[split]
    return SceneDataset(generate_scenes(params, split, count, progress), split)


__all__ = ["SCENE_FIELDS", "SceneDataset", "build_scenes", "collate_scenes", "farthest_point_sample",
           "make_scene_sample", "scenes_info"]
