"""The synthetic streets' layout: a straight street along +x (world frame, z up, ground at z = 0) built from boxes and
cylinders — road, sidewalks, parking strips, terrain, buildings, fences, trees, bushes, poles with signs, gravel
shoulders, parked and moving vehicles and people (each mover with an instance id and a constant velocity, none in the
ego car's way) — and the raw SemanticKITTI label of a ground point. :mod:`distilkit.data.synthetic` casts the ego
sensor's scans into it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from distilkit.data.classes import RAW_IDS
from distilkit.data.raycast import Primitives


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


def ground_labels(pts: np.ndarray, parking: np.ndarray, other_ground: np.ndarray | None = None) -> np.ndarray:
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

