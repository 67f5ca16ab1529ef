"""Camera images of the synthetic streets, cast with the LiDAR's ray caster (:mod:`distilkit.data.raycast`).

One ray per pixel centre from the camera (:mod:`distilkit.data.camera`) of the current frame or an earlier one
(the traffic moved back to where it was then). A pixel is shaded by its surface's class colour (SemanticKITTI's
palette), a Lambertian term of the surface normal under a fixed sun, and haze that grows with distance towards a
sky gradient; Gaussian noise is added. The depth map holds each hit's distance along the camera's z axis.

Images are drawn from the same street as the sample's LiDAR scans (:func:`~distilkit.data.synthetic.street`) but
from their own random stream, and cached apart from the scans: enabling the camera changes no LiDAR array.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from distilkit.data.cache import cached_samples
from distilkit.data.camera import CAMERA_IN_LIDAR, LIDAR_TO_CAMERA_AXES, frame_offsets, intrinsics, lidar_to_camera
from distilkit.data.classes import CLASS_COLOURS, remap, seg_lut
from distilkit.data.params import CameraParams, SyntheticParams
from distilkit.data.raycast import Primitives, cast
from distilkit.data.street_layout import SceneSpec
from distilkit.data.synthetic import hit_labels, lidar_params, street

CAMERA_VERSION = 1
SUN = np.array([0.35, 0.25, 0.9]) / np.linalg.norm([0.35, 0.25, 0.9])
SKY_TOP, SKY_HORIZON = np.array([0.45, 0.62, 0.88]), np.array([0.80, 0.85, 0.90])
HAZE = 70.0  # metres at which a surface keeps 1/e of its colour


def pixel_rays(p: CameraParams) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions through the pixel centres, row-major (H*W, 3), in the camera frame and the LiDAR frame."""
    k = intrinsics(p)
    v, u = np.meshgrid(np.arange(p.height) + 0.5, np.arange(p.width) + 0.5, indexing="ij")
    cam = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    cam /= np.linalg.norm(cam, axis=1, keepdims=True)
    return cam, cam @ LIDAR_TO_CAMERA_AXES  # the rotation's inverse is its transpose: d_lidar = R^T d_cam


def surface_normals(prims: Primitives, kind: np.ndarray, index: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """(R, 3) outward unit normals at the hits (``kind``/``index`` from :func:`cast`); zero where nothing is hit."""
    n = np.zeros((len(kind), 3))
    n[kind == 1] = (0.0, 0.0, 1.0)
    sel = np.flatnonzero(kind == 2)
    if sel.size:  # a box: the face the hit lies on (the nearest of the six planes)
        box, p = prims.boxes[index[sel]], xyz[sel]
        gaps = np.abs(np.concatenate([p - box[:, :3], box[:, 3:] - p], 1))  # (m, 6): lo x,y,z then hi x,y,z
        face = gaps.argmin(1)
        n[sel, face % 3] = np.where(face < 3, -1.0, 1.0)
    sel = np.flatnonzero(kind == 3)
    if sel.size:  # a vertical cylinder: its top or its side
        cyl, p = prims.cylinders[index[sel]], xyz[sel]
        top = np.abs(p[:, 2] - cyl[:, 3]) < 1e-3
        side = np.concatenate([(p[:, :2] - cyl[:, :2]) / cyl[:, 4:5], np.zeros((len(sel), 1))], 1)
        n[sel] = np.where(top[:, None], np.array([0.0, 0.0, 1.0]), side)
    sel = np.flatnonzero(kind == 4)
    if sel.size:
        sph = prims.spheres[index[sel]]
        n[sel] = (xyz[sel] - sph[:, :3]) / sph[:, 3:4]
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def render(scene: SceneSpec, ego: np.ndarray, frame: int, p: CameraParams, ego_speed: float,
           rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The image (H, W, 3) uint8 and depth map (H, W) float32 of the camera at ``frame`` (0 = current, -k = k frames
    earlier); ``ego`` is the LiDAR's position at the current frame (world frame)."""
    cam, dirs = pixel_rays(p)
    origin = (ego + CAMERA_IN_LIDAR + np.array([frame * ego_speed, 0.0, 0.0])).astype(np.float32)
    prims = scene.prims.at_frame(frame).near(origin, p.max_depth + 10.0)
    t, kind, index, xyz = cast(origin, dirs.astype(np.float32), prims)
    depth = np.where(np.isfinite(t), t, 0.0) * cam[:, 2]
    hit = np.isfinite(t) & (depth <= p.max_depth)
    label, _ = hit_labels(scene, prims, kind, index, xyz)
    albedo = np.asarray(CLASS_COLOURS, np.float64)[remap(label, seg_lut())] / 255.0
    albedo[label == 0] = 0.5  # a surface of no class (none in these streets) is grey
    light = 0.35 + 0.65 * np.clip(surface_normals(prims, kind, index, xyz) @ SUN, 0.0, None)
    row = (np.arange(p.height).repeat(p.width) + 0.5) / p.height
    sky = SKY_TOP[None, :] + (SKY_HORIZON - SKY_TOP)[None, :] * np.clip(row * 2.0, 0.0, 1.0)[:, None]
    keep = np.exp(-depth / HAZE)[:, None]
    colour = np.where(hit[:, None], albedo * light[:, None] * keep + sky * (1.0 - keep), sky)
    colour = colour + rng.normal(0.0, p.noise, colour.shape)
    image = np.clip(np.round(colour * 255.0), 0, 255).astype(np.uint8).reshape(p.height, p.width, 3)
    return image, np.where(hit, depth, 0.0).astype(np.float32).reshape(p.height, p.width)


def make_camera_sample(seed: int, p: SyntheticParams) -> dict[str, np.ndarray]:
    """The camera fields of sample ``seed``: images of the current and earlier frames, their calibration, and the
    current frame's depth map."""
    assert p.camera is not None
    cp = p.camera
    _, scene, ego = street(seed, p)
    rng = np.random.default_rng([seed, 0xCA])  # the images' own stream: the scans' draws are untouched
    views = [render(scene, ego, frame, cp, p.ego_speed, rng) for frame in frame_offsets(cp)]  # current frame first
    images = [image for image, _ in views]
    k = intrinsics(cp).astype(np.float32)
    return {"image": np.stack(images), "depth": views[0][1],
            "intrinsics": np.stack([k] * len(images)),
            "lidar_to_camera": np.stack([lidar_to_camera(-f, p.ego_speed) for f in frame_offsets(cp)]).astype(np.float32)}


def generate_camera_split(p: SyntheticParams, split: str, count: int,
                          progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """The camera fields of ``count`` samples of ``split``, stacked (cached on disk apart from the scans)."""
    assert p.camera is not None
    key = {**lidar_params(p), "camera": p.camera.model_dump()}
    return cached_samples("synthetic-camera", CAMERA_VERSION, key, split, count, lambda seed: make_camera_sample(seed, p),
                          lambda samples: {k: np.stack([s[k] for s in samples]) for k in samples[0]}, progress)


__all__ = ["CAMERA_VERSION", "generate_camera_split", "make_camera_sample", "pixel_rays", "render", "surface_normals"]
