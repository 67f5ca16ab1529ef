"""Procedural LiDAR street scenes with SemanticKITTI classes, a driving ego sensor and SSC ground truth (the street's
layout is :mod:`distilkit.data.street_layout`'s; this module drives the sensor through it).

A scene is a straight street along +x (world frame, z up, ground at z = 0): a two-lane road,
raised sidewalks, parking strips, terrain, buildings, fences, trees (trunk + crown), bushes,
poles with traffic signs, gravel shoulders (other-ground), parked cars, trucks, motorcycles,
trailers (other-vehicle) and bicycles (static), and moving cars, trucks, buses, persons,
bicyclists and motorcyclists (each with an instance id and a constant velocity): all 19
SemanticKITTI classes. The ego sensor drives along the right lane at ``ego_speed`` metres per
frame, 1.73 m above the ground (KITTI); traffic in its lane never overlaps its footprint.

For one sample with current frame 0 (SemanticKITTI conventions, data_metrics.md §1.5):

* input: the current scan fused with the next ``input_frames - 1`` scans, all in the
  current sensor frame, each point tagged with its frame offset (the teacher uses more
  frames than the student);
* SSC ground truth: the current and next ``gt_frames`` scans voxelised on the SSC grid,
  majority raw label per voxel (ties to the smallest id), remapped with the SSC LUT
  (0 = empty); ``invalid`` marks voxels that no ray of those scans traversed or hit;
* scribble labels (ScribbleSC, Scribble2Scene §3): the same ground-truth points, but only those
  on BEV line scribbles (``lines``) or a random subset (``random``) carry their class; a voxel's
  scribble label is the majority over its labelled points, ``SCRIBBLE_UNLABELLED`` where it is
  occupied but holds none, 0 where empty, 255 where invalid.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from distilkit.data.cache import cached_samples
from distilkit.data.classes import IGNORE_INDEX, RAW_IDS, SCRIBBLE_UNLABELLED, remap, seg_lut, ssc_lut
from distilkit.data.raycast import Primitives, cast, ray_directions
from distilkit.data.params import SyntheticParams
from distilkit.data.street_layout import (EGO_LANE_Y, SENSOR_HEIGHT, REFLECTANCE, SceneSpec, ground_labels,
                                         make_scene)
from distilkit.structures import VoxelGrid

GENERATOR_VERSION = 2  # 2: ego-safe traffic, all 19 classes, scribbles, test split


@dataclass
class Scan:
    xyz: np.ndarray  # (n,3) world frame
    intensity: np.ndarray
    label: np.ndarray  # raw ids
    inst: np.ndarray
    origin: np.ndarray  # (3,) sensor position, world frame


def hit_labels(scene: SceneSpec, prims: Primitives, kind: np.ndarray, index: np.ndarray,
               xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw SemanticKITTI label and instance id of each ray's hit (``kind``/``index`` from :func:`cast` over
    ``prims``; ``xyz`` the hit points, world frame); 0 where nothing is hit."""
    label = np.zeros(len(kind), np.int64)
    inst = np.zeros(len(kind), np.int64)
    for k, lab, ins in ((2, prims.box_label, prims.box_inst), (3, prims.cyl_label, prims.cyl_inst),
                        (4, prims.sph_label, prims.sph_inst)):
        sel = kind == k
        label[sel], inst[sel] = lab[index[sel]], ins[index[sel]]
    g = kind == 1
    label[g] = ground_labels(xyz[g], scene.parking, scene.other_ground)
    return label, inst


def cast_scan(scene: SceneSpec, origin: np.ndarray, frame: int, dirs: np.ndarray, rng: np.random.Generator,
              max_range: float, range_noise: float) -> Scan:
    prims = scene.prims.at_frame(frame).near(origin, max_range + 5.0)
    t, kind, index, _ = cast(origin, dirs, prims)
    keep = np.isfinite(t) & (t <= max_range) & (t > 1.0)
    t = np.where(keep, t, 0) + rng.normal(0.0, range_noise, t.shape).astype(np.float32)
    xyz = origin[None, :] + dirs * t[:, None]
    label, inst = hit_labels(scene, prims, kind, index, xyz)
    names = {RAW_IDS[n]: n for n in REFLECTANCE}
    base = np.array([REFLECTANCE.get(names.get(int(l), ""), 0.4) for l in range(300)], np.float32)
    refl = base[np.clip(_static_id(label), 0, 299)]
    intensity = np.clip(refl + rng.normal(0, 0.05, len(t)).astype(np.float32), 0, 1)
    return Scan(xyz[keep].astype(np.float32), intensity[keep], label[keep], inst[keep], origin.astype(np.float32))


def _static_id(label: np.ndarray) -> np.ndarray:
    moving = {252: 10, 253: 31, 254: 30, 255: 32, 256: 16, 257: 13, 258: 18, 259: 20}
    out = label.copy()
    for m, s in moving.items():
        out[label == m] = s
    return out


def voxelize_majority(xyz: np.ndarray, raw: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """Majority raw label per voxel (ties -> smallest id), 0 where no point falls; (X,Y,Z) int64."""
    idx = np.floor((xyz - np.array(grid.origin, np.float32)) / grid.voxel_size).astype(np.int64)
    shape = np.array(grid.shape)
    inside = ((idx >= 0) & (idx < shape)).all(1)
    flat = np.ravel_multi_index(idx[inside].T, grid.shape)
    lab = raw[inside]
    out = np.zeros(int(np.prod(grid.shape)), np.int64)
    if flat.size:
        pairs, counts = np.unique(np.stack([flat, lab], 1), axis=0, return_counts=True)
        # sort by voxel, then count descending, then label ascending; first row per voxel wins
        order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
        pairs = pairs[order]
        first = np.ones(len(pairs), bool)
        first[1:] = pairs[1:, 0] != pairs[:-1, 0]
        out[pairs[first, 0]] = pairs[first, 1]
    return out.reshape(grid.shape)


def traversed(origins: list[np.ndarray], ends: list[np.ndarray], grid: VoxelGrid) -> np.ndarray:
    """(X,Y,Z) bool: voxels a ray passes through or ends in (sampled every half voxel)."""
    seen = np.zeros(int(np.prod(grid.shape)), bool)
    origin = np.array(grid.origin, np.float32)
    shape = np.array(grid.shape)
    step = 0.5  # in voxels
    for o, p in zip(origins, ends):
        if len(p) == 0:
            continue
        start = (o - origin) / grid.voxel_size
        vec = (p - o[None, :]) / grid.voxel_size
        length = np.linalg.norm(vec, axis=1)
        order = np.argsort(-length)
        length, vec = length[order], vec[order]
        unit = vec / np.maximum(length, 1e-6)[:, None]
        samples = [start[None, :] + vec]  # the end points themselves
        n_active = len(length)
        k = 0
        while True:
            s = k * step
            n_active = int(np.searchsorted(-length, -s, side="right"))
            if n_active == 0:
                break
            samples.append(start[None, :] + unit[:n_active] * s)
            k += 1
        q = np.floor(np.concatenate(samples)).astype(np.int64)
        ok = ((q >= 0) & (q < shape)).all(1)
        seen[np.ravel_multi_index(q[ok].T, grid.shape)] = True
    return seen.reshape(grid.shape)


def street(seed: int, p: SyntheticParams) -> tuple[np.random.Generator, SceneSpec, np.ndarray]:
    """The street of sample ``seed`` and the ego sensor's position at the current frame (world frame), with the
    generator that drew them (the LiDAR scans draw on from it; a camera renders the same street)."""
    rng = np.random.default_rng(seed)
    n_frames = max(p.input_frames, p.gt_frames + 1)
    x0 = rng.uniform(0, 20)
    scene = make_scene(rng, x0 - 20, x0 + p.ego_speed * n_frames + 80, p.ego_speed, x0, n_frames)
    return rng, scene, np.array([x0, EGO_LANE_Y, SENSOR_HEIGHT], np.float32)


def make_sample(seed: int, p: SyntheticParams) -> dict[str, np.ndarray]:
    """Generate one sample: fused input points with frame tags, SSC labels and the invalid mask."""
    rng, scene, ego0 = street(seed, p)
    grid = VoxelGrid.semantickitti(p.scale)
    n_frames = max(p.input_frames, p.gt_frames + 1)
    dirs = ray_directions(p.beams, p.azimuth_steps, p.fov_up, p.fov_down)
    scans = []
    for j in range(n_frames):
        origin = ego0 + np.array([p.ego_speed * j, 0, 0], np.float32)
        scans.append(cast_scan(scene, origin, j, dirs, rng, p.max_range, p.range_noise))
    # Current sensor frame = world - ego0 (the ego drives straight along +x, heading 0).
    to_cur = lambda xyz: xyz - ego0[None, :]  # noqa: E731
    inp = scans[: p.input_frames]
    points = np.concatenate([np.concatenate([to_cur(s.xyz), s.intensity[:, None]], 1) for s in inp]).astype(np.float32)
    frame = np.concatenate([np.full(len(s.xyz), j, np.uint8) for j, s in enumerate(inp)])
    raw = np.concatenate([s.label for s in inp])
    inst = np.concatenate([s.inst for s in inp])
    gt = scans[: p.gt_frames + 1]
    gt_xyz = np.concatenate([to_cur(s.xyz) for s in gt])
    gt_raw = np.concatenate([s.label for s in gt])
    voxel_raw = voxelize_majority(gt_xyz, gt_raw, grid)
    seen = traversed([to_cur(s.origin[None])[0] for s in gt], [to_cur(s.xyz) for s in gt], grid)
    invalid = ~seen & (voxel_raw == 0)
    scribble = scribble_labels(gt_xyz, gt_raw, gt_xyz + ego0[None, :], voxel_raw, invalid, grid, p, rng)
    return {
        "points": points,
        "point_frame": frame,
        "point_label": remap(raw, seg_lut()).astype(np.uint8),
        "point_raw": raw.astype(np.uint32) | (inst.astype(np.uint32) << 16),
        "voxel_label": remap(voxel_raw, ssc_lut()).astype(np.uint8),
        "invalid": invalid,
        "scribble": scribble,
    }


def scribble_mask(world_xyz: np.ndarray, p: SyntheticParams, rng: np.random.Generator) -> np.ndarray:
    """(n,) bool: the ground-truth points an annotator labels.

    ``lines``: two families of parallel BEV lines (random orientations and offsets, fixed in the
    world, ``scribble_spacing`` m apart, ``scribble_width`` m wide), as ScribbleKITTI's line
    scribbles on accumulated scans (about 2 * width / spacing of the points; 8 % there).
    ``random``: each point with probability ``scribble_fraction`` (Scribble2Scene's SemanticPOSS
    variant: 10 % of the full annotation).
    """
    if p.scribble == "random":
        return rng.random(len(world_xyz)) < p.scribble_fraction
    keep = np.zeros(len(world_xyz), bool)
    for _ in range(2):
        theta = rng.uniform(0, np.pi)
        normal = np.array([np.cos(theta), np.sin(theta)], np.float64)
        d = world_xyz[:, :2].astype(np.float64) @ normal + rng.uniform(0, p.scribble_spacing)
        keep |= np.abs(d - p.scribble_spacing * np.round(d / p.scribble_spacing)) < p.scribble_width / 2
    return keep


def scribble_labels(xyz: np.ndarray, raw: np.ndarray, world_xyz: np.ndarray, voxel_raw: np.ndarray,
                    invalid: np.ndarray, grid: VoxelGrid, p: SyntheticParams, rng: np.random.Generator) -> np.ndarray:
    """(X,Y,Z) uint8 ScribbleSC labels: class ids of scribbled voxels, ``SCRIBBLE_UNLABELLED`` for
    occupied voxels without a scribbled point, 0 for empty, 255 for invalid."""
    keep = scribble_mask(world_xyz, p, rng)
    lab = remap(voxelize_majority(xyz[keep], raw[keep], grid), ssc_lut())
    out = np.where(voxel_raw != 0, SCRIBBLE_UNLABELLED, 0)
    labelled = (lab != 0) & (lab != IGNORE_INDEX)
    out = np.where(labelled & (voxel_raw != 0), lab, out)
    out = np.where(invalid, IGNORE_INDEX, out)
    return out.astype(np.uint8)


_ARRAYS = ("points", "point_frame", "point_label", "point_raw")
_GRIDS = ("voxel_label", "invalid", "scribble")


def generate_split(p: SyntheticParams, split: str, count: int,
                   progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """Generate (or load from the on-disk cache) ``count`` samples of ``split``; arrays stacked with offsets."""
    def stack(samples: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        out = {k: np.concatenate([s[k] for s in samples]) for k in _ARRAYS}
        out["offsets"] = np.cumsum([0] + [len(s["points"]) for s in samples]).astype(np.int64)
        out.update({k: np.stack([s[k] for s in samples]) for k in _GRIDS})
        return out

    return cached_samples("synthetic-lidar", GENERATOR_VERSION, lidar_params(p), split, count,
                          lambda seed: make_sample(seed, p), stack, progress)


def lidar_params(p: SyntheticParams) -> dict[str, object]:
    """The parameters that shape the LiDAR arrays (all but the camera's: adding a camera keeps the scans)."""
    return p.model_dump(exclude={"camera"})
