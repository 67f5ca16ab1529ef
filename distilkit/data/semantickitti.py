"""SemanticKITTI file formats (data_metrics.md §1): scans, point labels, SSC voxel files, poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from distilkit.errors import DataError

VOXEL_SHAPE = (256, 256, 32)


def _read(path: Path, dtype: np.dtype, what: str, multiple: int = 1) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    size = path.stat().st_size
    if size % (np.dtype(dtype).itemsize * multiple):
        raise DataError(
            f"{path}: {what} file has {size} bytes, not a multiple of {np.dtype(dtype).itemsize * multiple} "
            f"(truncated or not a SemanticKITTI {what} file)"
        )
    return np.fromfile(path, dtype=dtype)


def read_points(path: str | Path) -> np.ndarray:
    """``velodyne/NNNNNN.bin``: little-endian float32 (N, 4) = x, y, z, remission; at least one point, every
    coordinate finite."""
    from distilkit.data.pointfiles import check_finite

    points = _read(Path(path), np.dtype("<f4"), "point cloud", 4).reshape(-1, 4)
    if len(points) == 0:
        raise DataError(f"{path}: the scan holds no point (an empty file)")
    return check_finite(points, path)


def read_point_labels(path: str | Path, num_points: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``labels/NNNNNN.label``: uint32 per point -> (semantic = lower 16 bits, instance = upper 16 bits)."""
    raw = _read(Path(path), np.dtype("<u4"), "point label")
    if num_points is not None and raw.size != num_points:
        raise DataError(f"{path}: {raw.size} labels for {num_points} points")
    return (raw & 0xFFFF).astype(np.int64), (raw >> 16).astype(np.int64)


def write_point_labels(path: str | Path, semantic: np.ndarray, instance: np.ndarray) -> None:
    ((np.asarray(instance, np.uint32) << 16) | np.asarray(semantic, np.uint32)).astype("<u4").tofile(path)


def unpack_bits(packed: np.ndarray) -> np.ndarray:
    """MSB-first bit unpacking (voxel 8b is bit 7 of byte b), as ``np.unpackbits``."""
    return np.unpackbits(packed.astype(np.uint8)).astype(bool)


def pack_bits(bits: np.ndarray) -> np.ndarray:
    return np.packbits(np.asarray(bits).reshape(-1) > 0)


def read_voxel_bits(path: str | Path, shape: tuple[int, int, int] = VOXEL_SHAPE) -> np.ndarray:
    """``voxels/*.bin|.invalid|.occluded``: bit-packed, C-order (X, Y, Z)."""
    n = int(np.prod(shape))
    packed = _read(Path(path), np.dtype(np.uint8), "packed voxel")
    if packed.size * 8 != n:
        raise DataError(f"{path}: {packed.size} bytes, expected {n // 8} for a {shape} grid")
    return unpack_bits(packed).reshape(shape)


def read_voxel_labels(path: str | Path, shape: tuple[int, int, int] = VOXEL_SHAPE) -> np.ndarray:
    """``voxels/NNNNNN.label``: uint16 raw ids per voxel, C-order (X, Y, Z)."""
    raw = _read(Path(path), np.dtype("<u2"), "voxel label")
    if raw.size != int(np.prod(shape)):
        raise DataError(f"{path}: {raw.size} voxel labels, expected {int(np.prod(shape))} for a {shape} grid")
    return raw.reshape(shape)


def write_voxel_labels(path: str | Path, raw: np.ndarray) -> None:
    np.asarray(raw).astype("<u2").reshape(-1).tofile(path)


def write_voxel_bits(path: str | Path, bits: np.ndarray) -> None:
    pack_bits(bits).tofile(path)


def read_calib(path: str | Path) -> dict[str, np.ndarray]:
    """``calib.txt``: ``KEY: 12 floats`` -> 4x4 matrices."""
    out: dict[str, np.ndarray] = {}
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: calibration file not found")
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        key, _, vals = line.partition(":")
        try:
            m = np.array([float(v) for v in vals.split()], dtype=np.float64)
        except ValueError:
            raise DataError(f"{path}:{n}: expected 'KEY: 12 numbers'") from None
        if m.size != 12:
            raise DataError(f"{path}:{n}: expected 12 numbers after {key!r}, got {m.size}")
        out[key.strip()] = np.vstack([m.reshape(3, 4), [0, 0, 0, 1]])
    return out


def read_poses(path: str | Path, calib: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """``poses.txt`` (cam0 frame) -> (F, 4, 4) LiDAR-frame poses ``inv(Tr) @ P @ Tr`` (§1.4)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: poses file not found")
    rows = []
    for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = [float(v) for v in line.split()]
        except ValueError:
            raise DataError(f"{path}:{n}: a pose line must be 12 numbers, got {line.strip()[:80]!r}") from None
        if len(values) != 12:
            raise DataError(f"{path}:{n}: a pose line must have 12 numbers, got {len(values)}")
        rows.append(values)
    if not rows:
        raise DataError(f"{path}: no pose in the file")
    rows = np.asarray(rows, dtype=np.float64)
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    if calib is not None and "Tr" in calib:
        tr = calib["Tr"]
        poses = np.linalg.inv(tr) @ poses @ tr
    return poses
