"""Procedural LiDAR street scenes with SemanticKITTI classes, a driving ego sensor and SSC ground truth.

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

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from distilkit.data.cache import cached_samples
from distilkit.data.classes import IGNORE_INDEX, RAW_IDS, SCRIBBLE_UNLABELLED, remap, seg_lut, ssc_lut
from distilkit.data.raycast import Primitives, cast, ray_directions
from distilkit.data.params import SyntheticParams
from distilkit.structures import VoxelGrid

GENERATOR_VERSION = 2  # 2: ego-safe traffic, all 19 classes, scribbles, test split
SENSOR_HEIGHT = 1.73
ROAD_HALF = 4.0
SIDEWALK_OUT = 6.5
REFLECTANCE = {"road": 0.25, "sidewalk": 0.35, "parking": 0.3, "terrain": 0.45, "building": 0.5, "fence": 0.4,
               "vegetation": 0.6, "trunk": 0.4, "pole": 0.55, "traffic-sign": 0.9, "car": 0.7, "truck": 0.65,
               "person": 0.35, "bicyclist": 0.45, "bicycle": 0.5, "motorcycle": 0.6, "other-vehicle": 0.6,
               "motorcyclist": 0.45, "other-ground": 0.3, "bus": 0.65}
EGO_HALF_LENGTH = 2.6  # the ego car's footprint around the sensor along x (metres)
EGO_LANE_Y = -1.75


@dataclass
class SceneSpec:
    prims: Primitives
    parking: np.ndarray  # (S,2) x ranges of parking strips on the left side
    other_ground: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))  # right shoulder x ranges


class _Builder:
    def __init__(self) -> None:
        self.boxes: list[tuple] = []
        self.cyls: list[tuple] = []
        self.sphs: list[tuple] = []
        self.next_inst = 1

    def inst(self) -> int:
        self.next_inst += 1
        return self.next_inst - 1

    def box(self, lo, hi, name, inst=0, vel=(0.0, 0.0)):
        self.boxes.append((list(lo) + list(hi), RAW_IDS[name], inst, vel))

    def cyl(self, cx, cy, z0, z1, r, name, inst=0, vel=(0.0, 0.0)):
        self.cyls.append(([cx, cy, z0, z1, r], RAW_IDS[name], inst, vel))

    def sph(self, cx, cy, cz, r, name, inst=0, vel=(0.0, 0.0)):
        self.sphs.append(([cx, cy, cz, r], RAW_IDS[name], inst, vel))

    def build(self) -> Primitives:
        def arrs(items, width):
            if not items:
                return (np.zeros((0, width), np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64),
                        np.zeros((0, 2), np.float32))
            return (np.array([i[0] for i in items], np.float32), np.array([i[1] for i in items], np.int64),
                    np.array([i[2] for i in items], np.int64), np.array([i[3] for i in items], np.float32))

        return Primitives(*arrs(self.boxes, 6), *arrs(self.cyls, 5), *arrs(self.sphs, 4))


def clear_of_ego(x_lo: float, length: float, v: float, ego_x0: float, ego_speed: float, n_frames: int,
                 margin: float = 2.0) -> bool:
    """True if a box in the ego lane (rear at ``x_lo``, moving ``v`` m/frame) keeps ``margin`` metres
    from the ego footprint at every frame 0..n_frames (the gap is linear in time: check the ends)."""
    for j in (0, n_frames):
        ego = ego_x0 + ego_speed * j
        lo, hi = x_lo + v * j, x_lo + length + v * j
        if hi > ego - EGO_HALF_LENGTH - margin and lo < ego + EGO_HALF_LENGTH + margin:
            return False
    ahead0 = x_lo > ego_x0  # the box must stay on the same side of the ego throughout
    aheadn = x_lo + v * n_frames > ego_x0 + ego_speed * n_frames
    return ahead0 == aheadn


def make_scene(rng: np.random.Generator, x_min: float, x_max: float, ego_speed: float,
               ego_x0: float | None = None, n_frames: int = 0) -> SceneSpec:
    """Lay out one street between ``x_min`` and ``x_max`` (metres, world frame).

    ``ego_x0`` / ``n_frames``: the ego's start and trajectory length, kept clear of its lane's
    traffic; the rarer classes are placed at least once in its forward view.
    """
    ego_x0 = x_min + 20 if ego_x0 is None else ego_x0
    view = (ego_x0 + 4.0, ego_x0 + 45.0)  # in front of the sensor, inside the 51.2 m SSC volume
    b = _Builder()
    # Parking strips on the left; sidewalks elsewhere (raised 15 cm).
    parking, x = [], x_min
    while x < x_max:
        seg = rng.uniform(10, 25)
        if rng.random() < 0.35:
            parking.append((x, x + seg))
        else:
            b.box((x, ROAD_HALF, 0), (x + seg, SIDEWALK_OUT, 0.15), "sidewalk")
        x += seg
    b.box((x_min, -SIDEWALK_OUT, 0), (x_max, -ROAD_HALF, 0.15), "sidewalk")
    for side in (-1, 1):
        # Buildings with gaps, fences, trees, bushes, poles and signs.
        x = x_min + rng.uniform(0, 5)
        while x < x_max:
            w = rng.uniform(8, 25)
            if rng.random() < 0.75:
                y0 = rng.uniform(11, 16)
                lo_y, hi_y = sorted((side * y0, side * (y0 + rng.uniform(6, 12))))
                b.box((x, lo_y, 0), (x + w, hi_y, rng.uniform(4, 14)), "building")
            x += w + rng.uniform(1, 6)
        x = x_min + rng.uniform(0, 8)
        while x < x_max:
            w = rng.uniform(5, 15)
            y = side * rng.uniform(8.5, 10)
            b.box((x, min(y, y + side * 0.1), 0), (x + w, max(y, y + side * 0.1), rng.uniform(1.0, 1.8)), "fence")
            x += w + rng.uniform(4, 15)
        x = x_min + rng.uniform(0, 6)
        while x < x_max:
            y = side * rng.uniform(7.0, 8.2)
            h = rng.uniform(1.8, 3.0)
            b.cyl(x, y, 0, h, rng.uniform(0.15, 0.3), "trunk")
            b.sph(x, y, h + rng.uniform(1.0, 1.8), rng.uniform(1.4, 2.4), "vegetation")
            x += rng.uniform(6, 14)
        for _ in range(int((x_max - x_min) / 12)):
            xb, yb = rng.uniform(x_min, x_max), side * rng.uniform(6.8, 10.5)
            r = rng.uniform(0.5, 1.2)
            b.box((xb - r, yb - r, 0), (xb + r, yb + r, rng.uniform(0.5, 1.3)), "vegetation")
        x = x_min + rng.uniform(0, 10)
        while x < x_max:
            y = side * rng.uniform(6.6, 6.9)
            h = rng.uniform(4, 7)
            b.cyl(x, y, 0, h, 0.12, "pole")
            if rng.random() < 0.5:
                zs = rng.uniform(2.0, 2.8)
                b.box((x - 0.05, y - 0.35, zs), (x + 0.05, y + 0.35, zs + 0.7), "traffic-sign")
            x += rng.uniform(12, 30)
    # Parked vehicles in the parking strips (static ids).
    for lo, hi in parking:
        x = lo + rng.uniform(0.5, 3)
        while x < hi - 4:
            if rng.random() < 0.8:
                truck = rng.random() < 0.15
                length, width, height = (7.5, 2.4, 3.2) if truck else (4.2, 1.8, 1.5)
                if x + length > hi:
                    break
                y = (ROAD_HALF + SIDEWALK_OUT) / 2
                b.box((x, y - width / 2, 0), (x + length, y + width / 2, height), "truck" if truck else "car", b.inst())
                x += length
            x += rng.uniform(0.8, 3)
    # Moving traffic: oncoming cars on the left lane, cars/trucks ahead on the right lane.
    for _ in range(rng.integers(2, 6)):
        x, v = rng.uniform(x_min, x_max), -rng.uniform(0.6, 1.5) * max(ego_speed, 0.5)
        b.box((x, 0.85, 0), (x + 4.3, 2.65, 1.5), "moving-car", b.inst(), (v, 0.0))
    if rng.random() < 0.7:  # an oncoming bus (other-vehicle), in view
        x, v = rng.uniform(*view), -rng.uniform(0.5, 1.0) * max(ego_speed, 0.5)
        b.box((x, 0.75, 0), (x + 11.0, 3.25, 3.2), "moving-bus", b.inst(), (v, 0.0))
    for _ in range(rng.integers(1, 4)):  # the ego's lane: placed so that the ego never drives into them
        truck = rng.random() < 0.2
        length, width, height = (8.0, 2.5, 3.3) if truck else (4.3, 1.8, 1.5)
        for _try in range(20):
            x, v = rng.uniform(x_min, x_max), rng.uniform(0.3, 1.2) * max(ego_speed, 0.5)
            if clear_of_ego(x, length, v, ego_x0, ego_speed, n_frames):
                b.box((x, EGO_LANE_Y - width / 2, 0), (x + length, EGO_LANE_Y + width / 2, height),
                      "moving-truck" if truck else "moving-car", b.inst(), (v, 0.0))
                break
    for k in range(rng.integers(1, 3)):  # motorcyclists on the oncoming lane (one in view)
        x = rng.uniform(*view) if k == 0 else rng.uniform(x_min, x_max)
        v = -rng.uniform(0.8, 1.5) * max(ego_speed, 0.5)
        b.box((x, 1.3, 0), (x + 2.1, 2.1, 1.6), "moving-motorcyclist", b.inst(), (v, 0.0))
    # Pedestrians on the sidewalks (some standing), bicyclists at the road edge.
    for _ in range(rng.integers(2, 8)):
        side = rng.choice([-1, 1])
        x, y = rng.uniform(x_min, x_max), side * rng.uniform(4.5, 6.0)
        v = rng.choice([-1, 1]) * rng.uniform(0.1, 0.18) if rng.random() < 0.7 else 0.0
        b.cyl(x, y, 0.15, 0.15 + rng.uniform(1.55, 1.9), 0.28, "moving-person" if v else "person", b.inst(), (v, 0.0))
    for _ in range(rng.integers(0, 3)):
        x, v = rng.uniform(x_min, x_max), rng.uniform(0.35, 0.6)
        b.box((x, -3.7, 0), (x + 1.8, -3.1, 1.75), "moving-bicyclist", b.inst(), (v, 0.0))
    # Parked bicycles and a motorcycle on the right sidewalk (one of each in view).
    for k in range(rng.integers(1, 4)):
        x = rng.uniform(*view) if k == 0 else rng.uniform(x_min, x_max)
        b.box((x, -5.2, 0.15), (x + 1.7, -4.6, 1.2), "bicycle", b.inst())
    x = rng.uniform(*view)
    b.box((x, -6.3, 0.15), (x + 2.1, -5.5, 1.35), "motorcycle", b.inst())
    # Gravel shoulders (other-ground) behind the right sidewalk, one in view.
    shoulders = [(view[0] + rng.uniform(0, 15), 0.0)]
    shoulders[0] = (shoulders[0][0], shoulders[0][0] + rng.uniform(8, 20))
    x = x_min
    while x < x_max:
        seg = rng.uniform(6, 20)
        if rng.random() < 0.25:
            shoulders.append((x, x + seg))
        x += seg + rng.uniform(10, 30)
    return SceneSpec(b.build(), np.array(parking, np.float32).reshape(-1, 2),
                     np.array(shoulders, np.float32).reshape(-1, 2))


def _ground_labels(pts: np.ndarray, parking: np.ndarray, other_ground: np.ndarray | None = None) -> np.ndarray:
    y, x = pts[:, 1], pts[:, 0]
    lab = np.full(len(pts), RAW_IDS["terrain"], np.int64)
    lab[np.abs(y) < ROAD_HALF] = RAW_IDS["road"]
    left = (y >= ROAD_HALF) & (y < SIDEWALK_OUT)
    in_park = np.zeros(len(pts), bool)
    for lo, hi in parking:
        in_park |= (x >= lo) & (x < hi)
    lab[left & in_park] = RAW_IDS["parking"]
    lab[left & ~in_park] = RAW_IDS["sidewalk"]  # under a sidewalk box (rarely visible)
    lab[(y <= -ROAD_HALF) & (y > -SIDEWALK_OUT)] = RAW_IDS["sidewalk"]
    if other_ground is not None:
        shoulder = (y <= -SIDEWALK_OUT) & (y > -SIDEWALK_OUT - 2.5)
        for lo, hi in other_ground:
            lab[shoulder & (x >= lo) & (x < hi)] = RAW_IDS["other-ground"]
    return lab


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
    label[g] = _ground_labels(xyz[g], scene.parking, scene.other_ground)
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
