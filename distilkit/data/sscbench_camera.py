"""SSCBench-KITTI-360's left perspective camera as the batch fields of :mod:`distilkit.data.camera` (``image``,
``intrinsics``, ``lidar_to_camera``, ``depth``): what is read, and from where.

* the image: ``data_2d_raw/<drive>/image_00/data_rect/FFFFFF.png`` (the frame's own number; 1408 x 376 rectified,
  dataset/KITTI-360/README.md of ai4ce/SSCBench at 9e767e1), resized to the requested size with its intrinsics
  (:func:`~distilkit.data.kitti_camera.resize`);
* the calibration, where the folder holds KITTI-360's ``calibration/perspective.txt`` (``P_rect_00``, ``R_rect_00``)
  and ``calibration/calib_cam_to_velo.txt`` (camera 0 -> Velodyne, 3 x 4): intrinsics ``P_rect_00[:, :3]``, LiDAR ->
  camera ``inv(cam_to_velo)``; else the same two matrices as SSCBench's MonoScene hard-codes them
  (``method/MonoScene/monoscene/data/kitti_360/kitti_360_dataset.py``, ``read_calib``), named in a note.
* Conflict: MonoScene's loader uses ``inv(cam_to_velo)`` as the LiDAR -> rectified camera transform, leaving out the
  rectifying rotation ``R_rect_00`` that KITTI-360's own convention puts in front of it. The default follows
  the benchmark's code; ``camera.rectify_rotation: true`` applies ``R_rect_00`` (read from ``perspective.txt``; the
  rotation is below a degree).
* the depth target: the sample's points (the occupied voxel centres of ``.bin``) projected into the image, the
  nearest per pixel (:func:`~distilkit.data.kitti_camera.sparse_depth`).
Only the current image is read: SSCBench renumbers KITTI-360's frames, so earlier images are not tied to poses here.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from distilkit.data.info import Camera
from distilkit.data.kitti_camera import read_image, resize, sparse_depth
from distilkit.errors import DataError

IMAGE_SIZE = (376, 1408)  # (H, W) of image_00/data_rect (SSCBench's README)
# kitti_360_dataset.py's read_calib: P (3 x 4, image_00 rectified) and cam2velo (3 x 4)
MONOSCENE_P = np.array([[552.554261, 0.0, 682.049453, 0.0], [0.0, 552.554261, 238.769549, 0.0], [0.0, 0.0, 1.0, 0.0]])
MONOSCENE_CAM_TO_VELO = np.array([[0.04307104361, -0.08829286498, 0.995162929, 0.8043914418],
                                  [-0.999004371, 0.007784614041, 0.04392796942, 0.2993489574],
                                  [-0.01162548558, -0.9960641394, -0.08786966659, -0.1770225824]])


def _numbers(path: Path, key: str, count: int, values: str) -> np.ndarray:
    try:
        out = np.array([float(v) for v in values.split()], np.float64)
    except ValueError:
        raise DataError(f"{path}: {key} must be {count} numbers") from None
    if out.size != count:
        raise DataError(f"{path}: {key} has {out.size} numbers, expected {count}")
    return out


def read_perspective(path: str | Path) -> dict[str, np.ndarray]:
    """KITTI-360's ``perspective.txt``: ``P_rect_00`` (3, 4) and ``R_rect_00`` (3, 3) (other keys are skipped)."""
    path = Path(path)
    wanted = {"P_rect_00": (3, 4), "R_rect_00": (3, 3)}
    out = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        key, sep, values = line.partition(":")
        if sep and key.strip() in wanted:
            shape = wanted[key.strip()]
            out[key.strip()] = _numbers(path, key.strip(), shape[0] * shape[1], values).reshape(shape)
    missing = [k for k in wanted if k not in out]
    if missing:
        raise DataError(f"{path}: no {' or '.join(missing)} (the camera reads P_rect_00 and R_rect_00)")
    return out


def calibration(root: str | Path, rectify_rotation: bool = False) -> tuple[np.ndarray, np.ndarray, str]:
    """(K (3, 3), LiDAR -> camera 0 (4, 4), where they came from) of the folder at ``root`` (module docstring)."""
    folder = Path(root).expanduser() / "calibration"
    persp, c2v_file = folder / "perspective.txt", folder / "calib_cam_to_velo.txt"
    if persp.is_file() != c2v_file.is_file():
        missing = c2v_file if persp.is_file() else persp
        raise DataError(f"{missing}: not found (the camera reads perspective.txt and calib_cam_to_velo.txt together)")
    if persp.is_file():
        calib = read_perspective(persp)
        p, r = calib["P_rect_00"], calib["R_rect_00"]
        c2v = _numbers(c2v_file, "the camera -> Velodyne transform", 12, c2v_file.read_text()).reshape(3, 4)
        source = "calibration/perspective.txt and calib_cam_to_velo.txt"
    else:
        p, r, c2v = MONOSCENE_P, np.eye(3), MONOSCENE_CAM_TO_VELO
        source = "SSCBench's MonoScene constants (no calibration/ folder)"
    if rectify_rotation and not persp.is_file():
        raise DataError(f"{persp}: not found (camera.rectify_rotation reads R_rect_00 from it)")
    k = p[:, :3]
    if abs(np.linalg.det(k)) < 1e-12:
        raise DataError(f"{source}: P_rect_00's left 3 x 3 block is singular, not a camera's intrinsics")
    cam_to_velo = np.vstack([c2v, [0, 0, 0, 1]])
    lidar_to_cam = np.linalg.inv(cam_to_velo)
    if rectify_rotation:
        rect = np.eye(4)
        rect[:3, :3] = r
        lidar_to_cam = rect @ lidar_to_cam
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(k, p[:, 3])  # zero for image_00, the reference camera
    return k.copy(), offset @ lidar_to_cam, source


def describe(params: Any) -> Camera:
    """The camera as :class:`~distilkit.data.info.DataInfo` describes it: the calibration at the requested size."""
    cam = params.camera
    k, t, _ = calibration(params.root, cam.rectify_rotation) if Path(params.root).expanduser().is_dir() else \
        (MONOSCENE_P[:, :3], np.linalg.inv(np.vstack([MONOSCENE_CAM_TO_VELO, [0, 0, 0, 1]])), "")
    _, k = resize(np.zeros((*IMAGE_SIZE, 3), np.uint8), k, cam.height, cam.width)
    return Camera("image_00", tuple(map(tuple, k.tolist())), tuple(map(tuple, t.tolist())), (cam.height, cam.width),
                  (0,), depth="sparse")


def camera_fields(root: Path, drive: str, frame: str, cam: Any, points: np.ndarray) -> dict[str, np.ndarray]:
    """The camera fields of one frame (one image: T = 1) and the points' sparse depth in it."""
    k0, t, _ = calibration(root, cam.rectify_rotation)
    image, k = resize(read_image(root / "data_2d_raw" / drive / "image_00" / "data_rect" / f"{frame}.png"), k0,
                      cam.height, cam.width)
    return {"image": image[None], "intrinsics": k[None].astype(np.float32),
            "lidar_to_camera": t[None].astype(np.float32),
            "depth": sparse_depth(points[:, :3].astype(np.float64), k, t, cam.height, cam.width, cam.max_depth)}


__all__ = ["IMAGE_SIZE", "MONOSCENE_CAM_TO_VELO", "MONOSCENE_P", "calibration", "camera_fields", "describe",
           "read_perspective"]
