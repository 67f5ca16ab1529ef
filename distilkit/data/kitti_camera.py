"""The left colour camera of a SemanticKITTI folder: ``image_2/NNNNNN.png`` and its calibration (data_metrics.md §1.4),
as the batch fields of :mod:`distilkit.data.camera` (``image``, ``intrinsics``, ``lidar_to_camera``, ``depth``).

* ``calib.txt``'s ``P2 = K [I | t]`` projects camera-0 coordinates into image 2, and ``Tr`` takes LiDAR points to
  camera 0, so LiDAR -> camera 2 is ``[I | K⁻¹ P2[:, 3]] · Tr`` with intrinsics ``K``;
* an earlier frame's camera sees the current LiDAR frame through the LiDAR poses:
  ``T_cam2 · inv(pose_j) · pose_t``;
* images are resized to the requested size (bilinear) and ``K`` scaled with them (pixel centres kept: ``c' = (c +
  0.5) s − 0.5``); at the image's own size nothing changes;
* the depth target is the current scan's points projected into the current image (the nearest per pixel, metres
  along the camera's z axis, 0 where no point falls) — the sparse LiDAR depth camera SSC models train on.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from distilkit.errors import DataError


def read_image(path: str | Path) -> np.ndarray:
    """``image_2/NNNNNN.png`` -> (H, W, 3) uint8 RGB (read with Pillow, which matplotlib depends on)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: image file not found")
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()
    except (UnidentifiedImageError, OSError, SyntaxError) as exc:
        raise DataError(f"{path}: not a readable image ({exc})") from None


def write_image(path: str | Path, image: np.ndarray) -> None:
    """(H, W, 3) uint8 -> a PNG (lossless: :func:`read_image` gives it back exactly)."""
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8), "RGB").save(path, format="PNG")


def cam2_calibration(calib: dict[str, np.ndarray], where: str = "calib.txt") -> tuple[np.ndarray, np.ndarray]:
    """(K (3, 3), LiDAR -> camera 2 (4, 4)) from a :func:`~distilkit.data.semantickitti.read_calib` dict."""
    missing = [key for key in ("P2", "Tr") if key not in calib]
    if missing:
        raise DataError(f"{where}: no {' or '.join(missing)} (the camera needs P2 and Tr)")
    k = calib["P2"][:3, :3]
    if abs(np.linalg.det(k)) < 1e-12:
        raise DataError(f"{where}: P2's left 3 x 3 block is singular, not a camera's intrinsics")
    offset = np.eye(4)
    offset[:3, 3] = np.linalg.solve(k, calib["P2"][:3, 3])
    return k.copy(), offset @ calib["Tr"]


def resize(image: np.ndarray, k: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The image resized to ``height`` x ``width`` (bilinear) and its intrinsics scaled to match."""
    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image, k
    from PIL import Image

    out = np.asarray(Image.fromarray(image).resize((width, height), Image.Resampling.BILINEAR), dtype=np.uint8)
    sx, sy = width / w, height / h
    scaled = k.copy()
    scaled[0, 0], scaled[1, 1] = k[0, 0] * sx, k[1, 1] * sy
    scaled[0, 2], scaled[1, 2] = (k[0, 2] + 0.5) * sx - 0.5, (k[1, 2] + 0.5) * sy - 0.5
    return out, scaled


def sparse_depth(xyz: np.ndarray, k: np.ndarray, lidar_to_camera: np.ndarray, height: int, width: int,
                 max_depth: float) -> np.ndarray:
    """(H, W) float32: the nearest of the points (N, 3, LiDAR frame) projected into each pixel, as depth along the
    camera's z axis (0: no point within ``max_depth``)."""
    cam = xyz @ lidar_to_camera[:3, :3].T + lidar_to_camera[:3, 3]
    ahead = (cam[:, 2] > 1e-3) & (cam[:, 2] <= max_depth)
    cam = cam[ahead]
    uv = cam @ k.T
    u = np.floor(uv[:, 0] / uv[:, 2]).astype(np.int64)
    v = np.floor(uv[:, 1] / uv[:, 2]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, v[inside] * width + u[inside], cam[inside, 2])
    return np.where(np.isfinite(depth), depth, 0.0).astype(np.float32).reshape(height, width)


def camera_sample(seq: Path, frame: int, offsets: tuple[int, ...], height: int, width: int, max_depth: float,
                  poses: np.ndarray | None, calib: dict[str, np.ndarray], scan: np.ndarray) -> dict[str, np.ndarray]:
    """The camera fields of ``frame``: the images of ``frame + offset`` for each offset (0 first; frames before the
    sequence's first repeat it), their intrinsics and LiDAR(current) -> camera transforms, and the current scan's
    sparse depth."""
    k0, t_cam = cam2_calibration(calib, str(seq / "calib.txt"))
    images, ks, ts = [], [], []
    for off in offsets:
        j = max(frame + off, 0)
        image, k = resize(read_image(seq / "image_2" / f"{j:06d}.png"), k0, height, width)
        rel = np.eye(4) if j == frame or poses is None else np.linalg.inv(poses[j]) @ poses[frame]
        images.append(image)
        ks.append(k)
        ts.append(t_cam @ rel)
    return {"image": np.stack(images), "intrinsics": np.stack(ks).astype(np.float32),
            "lidar_to_camera": np.stack(ts).astype(np.float32),
            "depth": sparse_depth(scan[:, :3].astype(np.float64), ks[0], ts[0], height, width, max_depth)}


__all__ = ["cam2_calibration", "camera_sample", "read_image", "resize", "sparse_depth", "write_image"]
