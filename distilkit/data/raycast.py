"""A vectorised LiDAR ray caster over boxes, vertical cylinders, spheres and a ground plane.

All primitives are axis-aligned and may move with a constant velocity (per frame). For every
ray the nearest positive hit over all primitives is found by evaluating the (rays x primitives)
intersection distances in blocks of rays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

INF = np.float32(np.inf)


@dataclass
class Primitives:
    """Scene primitives. Each array has one row per primitive.

    boxes: (P,6) lo xyz, hi xyz; cylinders: (P,5) cx, cy, z0, z1, r; spheres: (P,4) cx, cy, cz, r.
    ``*_label`` raw SemanticKITTI ids, ``*_inst`` instance ids, ``*_vel`` (P,2) xy metres per frame.
    """

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6), np.float32))
    box_label: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    box_inst: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    box_vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 5), np.float32))
    cyl_label: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cyl_inst: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cyl_vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))
    sph_label: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sph_inst: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    sph_vel: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))

    def at_frame(self, frame: int) -> "Primitives":
        """The primitives moved to their positions at ``frame``."""
        b = self.boxes.copy()
        b[:, [0, 1]] += self.box_vel * frame
        b[:, [3, 4]] += self.box_vel * frame
        c = self.cylinders.copy()
        c[:, :2] += self.cyl_vel * frame
        s = self.spheres.copy()
        s[:, :2] += self.sph_vel * frame
        return Primitives(b, self.box_label, self.box_inst, self.box_vel, c, self.cyl_label, self.cyl_inst,
                          self.cyl_vel, s, self.sph_label, self.sph_inst, self.sph_vel)

    def near(self, origin: np.ndarray, radius: float) -> "Primitives":
        """The primitives whose xy footprint lies within ``radius`` of ``origin``."""
        return _subset(self, origin, radius)


def _near(arr: np.ndarray, xy_lo: np.ndarray, xy_hi: np.ndarray, origin: np.ndarray, radius: float) -> np.ndarray:
    dx = np.maximum(np.maximum(xy_lo[:, 0] - origin[0], origin[0] - xy_hi[:, 0]), 0)
    dy = np.maximum(np.maximum(xy_lo[:, 1] - origin[1], origin[1] - xy_hi[:, 1]), 0)
    return dx * dx + dy * dy <= radius * radius


def _subset(prims: "Primitives", origin: np.ndarray, radius: float) -> "Primitives":
    b = _near(prims.boxes, prims.boxes[:, :2], prims.boxes[:, 3:5], origin, radius)
    c = _near(prims.cylinders, prims.cylinders[:, :2] - prims.cylinders[:, 4:5],
              prims.cylinders[:, :2] + prims.cylinders[:, 4:5], origin, radius)
    s = _near(prims.spheres, prims.spheres[:, :2] - prims.spheres[:, 3:4],
              prims.spheres[:, :2] + prims.spheres[:, 3:4], origin, radius)
    return Primitives(prims.boxes[b], prims.box_label[b], prims.box_inst[b], prims.box_vel[b],
                      prims.cylinders[c], prims.cyl_label[c], prims.cyl_inst[c], prims.cyl_vel[c],
                      prims.spheres[s], prims.sph_label[s], prims.sph_inst[s], prims.sph_vel[s])


def ray_directions(beams: int, azimuth_steps: int, fov_up: float, fov_down: float) -> np.ndarray:
    """(beams*azimuth_steps, 3) unit directions of a spinning LiDAR (degrees, x forward, z up)."""
    elev = np.deg2rad(np.linspace(fov_up, fov_down, beams, dtype=np.float64))
    azim = np.linspace(-np.pi, np.pi, azimuth_steps, endpoint=False, dtype=np.float64)
    e, a = np.meshgrid(elev, azim, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    return d.astype(np.float32)


def _box_t(o: np.ndarray, d: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Slab method; ``d`` has no exact zero components (see :func:`cast`)."""
    inv = 1.0 / d
    tmin = np.full((d.shape[0], boxes.shape[0]), -INF, np.float32)
    tmax = np.full((d.shape[0], boxes.shape[0]), INF, np.float32)
    for a in range(3):
        t1 = (boxes[None, :, a] - o[a]) * inv[:, a:a + 1]
        t2 = (boxes[None, :, a + 3] - o[a]) * inv[:, a:a + 1]
        np.maximum(tmin, np.minimum(t1, t2), out=tmin)
        np.minimum(tmax, np.maximum(t1, t2), out=tmax)
    return np.where((tmax >= tmin) & (tmin > 1e-4), tmin, INF)


def _cyl_t(o: np.ndarray, d: np.ndarray, cyl: np.ndarray) -> np.ndarray:
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    ox, oy = o[0] - cyl[None, :, 0], o[1] - cyl[None, :, 1]
    a = dx * dx + dy * dy
    b = 2 * (dx * ox + dy * oy)
    c = ox * ox + oy * oy - cyl[None, :, 4] ** 2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t_side = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
        z = o[2] + t_side * dz
        side_ok = (disc >= 0) & (t_side > 1e-4) & (z >= cyl[None, :, 2]) & (z <= cyl[None, :, 3])
        t_top = (cyl[None, :, 3] - o[2]) / dz
        px, py = ox + t_top * dx, oy + t_top * dy
        top_ok = (t_top > 1e-4) & (px * px + py * py <= cyl[None, :, 4] ** 2)
    t = np.where(side_ok, t_side, INF)
    return np.minimum(t, np.where(top_ok, t_top, INF))


def _sph_t(o: np.ndarray, d: np.ndarray, sph: np.ndarray) -> np.ndarray:
    oc = o[None, :] - sph[:, :3]  # (P,3)
    b = d @ oc.T  # (R,P)
    c = (oc * oc).sum(1)[None, :] - sph[None, :, 3] ** 2
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0))
    return np.where((disc >= 0) & (t > 1e-4), t, INF)


def cast(
    origin: np.ndarray,
    dirs: np.ndarray,
    prims: Primitives,
    ground_z: float = 0.0,
    block: int = 4096,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cast rays from ``origin`` (3,) along ``dirs`` (R,3).

    Returns (t (R,), kind (R,) 0 none / 1 ground / 2 box / 3 cylinder / 4 sphere, index of the hit
    primitive (R,), hit points (R,3)). ``t`` is inf where nothing is hit.
    """
    o = origin.astype(np.float32)
    dirs = np.where(np.abs(dirs) < 1e-9, np.float32(1e-9), dirs).astype(np.float32)
    r = dirs.shape[0]
    t_best = np.full(r, INF, np.float32)
    kind = np.zeros(r, np.int64)
    index = np.full(r, -1, np.int64)
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(dirs[:, 2] < 0, (ground_z - o[2]) / dirs[:, 2], INF)
    sel = np.isfinite(tg) & (tg > 0)
    t_best[sel] = tg[sel]
    kind[sel] = 1
    for start in range(0, r, block):
        d = dirs[start:start + block]
        sl = slice(start, start + block)
        for k, (arr, fn) in enumerate(((prims.boxes, _box_t), (prims.cylinders, _cyl_t), (prims.spheres, _sph_t)), 2):
            if arr.shape[0] == 0:
                continue
            t = fn(o, d, arr)
            j = t.argmin(axis=1)
            tj = t[np.arange(t.shape[0]), j]
            better = tj < t_best[sl]
            t_best[sl] = np.where(better, tj, t_best[sl])
            kind[sl] = np.where(better, k, kind[sl])
            index[sl] = np.where(better, j, index[sl])
    pts = o[None, :] + dirs * np.where(np.isfinite(t_best), t_best, 0)[:, None]
    return t_best, kind, index, pts
