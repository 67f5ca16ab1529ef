"""A small SSCBench-KITTI-360 folder written in the benchmark's layout (ai4ce/SSCBench's dataset/KITTI-360/README.md at
9e767e1): ``data_2d_raw/<drive>/voxels/FFFFFF.bin|.label|.invalid``, ``image_00/data_rect/FFFFFF.png``,
``preprocess/labels/<drive>/FFFFFF_1_1.npy|_1_8.npy`` and, on request, KITTI-360's ``calibration/`` files.

Each frame is a synthetic scene built in train ids first (the truth the tests compare against), then written with raw
ids chosen among those the benchmark's learning map sends to each class (this module's own transcription of
``kitti360.yaml``), some occupied voxels carrying ids it ignores, an invalid mask that also covers occupied voxels
(which the benchmark keeps), and the voxelised input as a subset of the occupied voxels.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

SHAPE = (256, 256, 32)
DRIVE = "2013_05_28_drive_{:04d}_sync"
# train id -> raw ids kitti360.yaml's learning_map sends to it
RAW_OF = {1: (10, 252), 2: (11,), 3: (15,), 4: (18, 258), 5: (13, 16, 20, 256, 257, 259), 6: (30, 254), 7: (40, 60),
          8: (44,), 9: (48,), 10: (49,), 11: (50,), 12: (51,), 13: (70,), 14: (72,), 15: (80,), 16: (81,), 17: (52,),
          18: (99,)}
IGNORED_RAW = (1, 31, 32, 71, 253, 255)  # outlier, bicyclist, motorcyclist, trunk, moving-bi/motorcyclist
# a calibration unlike MonoScene's constants, so that a test tells which was read
P_RECT = np.array([[600.0, 0.0, 700.0, 0.0], [0.0, 610.0, 190.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
_A = np.deg2rad(0.4)
R_RECT = np.array([[np.cos(_A), -np.sin(_A), 0.0], [np.sin(_A), np.cos(_A), 0.0], [0.0, 0.0, 1.0]])
CAM_TO_VELO = np.array([[0.0, 0.0, 1.0, 0.8], [-1.0, 0.0, 0.0, 0.3], [0.0, -1.0, 0.0, -0.2]])


@dataclass
class Frame:
    truth: np.ndarray  # (X, Y, Z) the benchmark's target: train ids 0..18, 255 ignored
    raw: np.ndarray  # uint16 raw ids written to .label
    invalid: np.ndarray  # bool, written to .invalid (one byte a voxel)
    occupied_input: np.ndarray  # bool, written to .bin (bit-packed)


def scene(seed: int) -> Frame:
    """One frame: ground, boxes of every class, ignored raw ids, an invalid mask over empty and occupied voxels."""
    rng = np.random.default_rng(seed)
    ids = np.zeros(SHAPE, np.int64)
    ids[:, :, 7] = 14  # terrain
    ids[:, 96:160, 7] = 7  # road
    ids[:, 80:96, 7] = 9  # sidewalk
    for c in list(range(1, 19)) * 3:
        x, y = rng.integers(0, 240), rng.integers(0, 240)
        dx, dy, dz = rng.integers(2, 16), rng.integers(2, 16), rng.integers(1, 12)
        ids[x:x + dx, y:y + dy, 8:8 + dz] = c
    raw = np.zeros(SHAPE, np.int64)
    for c, options in RAW_OF.items():
        where = ids == c
        raw[where] = rng.choice(options, size=int(where.sum()))
    ignored = (rng.random(SHAPE) < 0.02) & (ids > 0)
    raw[ignored] = rng.choice(IGNORED_RAW, size=int(ignored.sum()))
    invalid = np.zeros(SHAPE, bool)
    invalid[200:, :, :] = True  # far away: unobserved, occupied or not
    invalid |= rng.random(SHAPE) < 0.1
    truth = ids.copy()
    truth[ignored] = 255
    truth[invalid & (raw == 0)] = 255
    occupied_input = (raw > 0) & (rng.random(SHAPE) < 0.3) & ~invalid
    assert (invalid & (raw > 0)).any() and (invalid & (raw == 0)).any() and ignored.any()
    return Frame(truth.astype(np.uint8), raw.astype(np.uint16), invalid, occupied_input)


def image(seed: int, height: int = 376, width: int = 1408) -> np.ndarray:
    """A smooth (H, W, 3) uint8 image (compresses well as PNG), different for every seed."""
    yy, xx = np.mgrid[0:height, 0:width]
    return np.stack([(xx + seed * 7) % 256, (yy * 2 + seed) % 256, (xx + yy) % 256], -1).astype(np.uint8)


def write_frame(root: Path, drive: str, frame: str, f: Frame, seed: int, images: bool = True) -> None:
    """One frame in the benchmark's files."""
    from PIL import Image

    vox = root / "data_2d_raw" / drive / "voxels"
    vox.mkdir(parents=True, exist_ok=True)
    f.raw.astype("<u2").reshape(-1).tofile(vox / f"{frame}.label")
    f.invalid.astype(np.uint8).reshape(-1).tofile(vox / f"{frame}.invalid")
    np.packbits(f.occupied_input.reshape(-1)).tofile(vox / f"{frame}.bin")
    labels = root / "preprocess" / "labels" / drive
    labels.mkdir(parents=True, exist_ok=True)
    np.save(labels / f"{frame}_1_1.npy", f.truth.astype(np.float32))  # preprocess.py saves float32
    np.save(labels / f"{frame}_1_8.npy", f.truth[::8, ::8, ::8].astype(np.float32))  # layout only: never read
    if images:
        cam = root / "data_2d_raw" / drive / "image_00" / "data_rect"
        cam.mkdir(parents=True, exist_ok=True)
        Image.fromarray(image(seed), "RGB").save(cam / f"{frame}.png")


def write_calibration(root: Path) -> None:
    """KITTI-360's ``calibration/perspective.txt`` (with keys the reader skips) and ``calib_cam_to_velo.txt``."""
    folder = root / "calibration"
    folder.mkdir(parents=True, exist_ok=True)
    row = lambda m: " ".join(f"{v:.12e}" for v in np.asarray(m).reshape(-1))  # noqa: E731
    folder.joinpath("perspective.txt").write_text(
        "calib_time: 09-Jan-2012 14:00:15\ncorner_dist: 9.950000e-02\nS_rect_00: 1.408000e+03 3.760000e+02\n"
        f"R_rect_00: {row(R_RECT)}\nP_rect_00: {row(P_RECT)}\nS_rect_01: 1.408000e+03 3.760000e+02\n")
    folder.joinpath("calib_cam_to_velo.txt").write_text(row(CAM_TO_VELO) + "\n")


# drive number -> frames written (every 5th, as the benchmark's)
LAYOUT = {0: ("000000",), 6: ("000000", "000005"), 9: ("000010",)}


def write_folder(root: Path, layout: dict[int, tuple[str, ...]] | None = None, images: bool = True,
                 calibration: bool = False) -> dict[tuple[str, str], Frame]:
    """The folder at ``root`` (the benchmark's KITTI-360 folder); returns each (drive, frame)'s :class:`Frame`."""
    out = {}
    for n, (number, frames) in enumerate(sorted((layout or LAYOUT).items())):
        drive = DRIVE.format(number)
        for k, frame in enumerate(frames):
            seed = 100 * n + k
            out[(drive, frame)] = f = scene(seed)
            write_frame(root, drive, frame, f, seed, images)
    if calibration:
        write_calibration(root)
    return out


def write_prediction(folder: Path, drive: str, frame: str, train_ids: np.ndarray, raw: bool = False,
                     seed: int = 0) -> None:
    """A prediction as ``<drive>/FFFFFF_1_1.npy`` (train ids) or, with ``raw``, ``<drive>/FFFFFF.label`` (uint16 raw
    ids drawn among each class's)."""
    d = folder / drive
    d.mkdir(parents=True, exist_ok=True)
    if not raw:
        np.save(d / f"{frame}_1_1.npy", train_ids.astype(np.uint8))
        return
    rng = np.random.default_rng(seed)
    out = np.zeros(SHAPE, np.int64)
    for c, options in RAW_OF.items():
        where = train_ids == c
        out[where] = rng.choice(options, size=int(where.sum()))
    out.astype("<u2").reshape(-1).tofile(d / f"{frame}.label")
