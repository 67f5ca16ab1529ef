"""SSCBench-KITTI-360 (Li et al., SSCBench, IROS 2024): its folder layout, file formats, class table and splits, and
the folder as a dataset (``sscbench-kitti360``). Facts from ai4ce/SSCBench at commit 9e767e1 (2025-04-09):
``dataset/KITTI-360/README.md`` (layout, sizes, splits), ``dataset/configs/kitti360.yaml`` (labels, colours, learning
map, splits), ``method/MonoScene/monoscene/data/kitti_360/io_data.py`` (file formats) and ``preprocess.py`` (the
target). The data is CC BY-NC-SA 3.0: nothing of it is bundled; a user points ``root`` at their own copy.

The root is the benchmark's ``KITTI-360`` folder:

* ``data_2d_raw/2013_05_28_drive_NNNN_sync/voxels/FFFFFF.label``: uint16 raw ids (SemanticKITTI's ids, mapped by
  ``kitti360.yaml``'s learning map), one per voxel of the 256 x 256 x 32 grid at 0.2 m, C order (X, Y, Z), every 5th
  frame;
* ``voxels/FFFFFF.invalid``: the voxels no LiDAR ray observed, **one byte a voxel** (``io_data.py`` reads it without
  unpacking, unlike SemanticKITTI's bit-packed files); a bit-packed file (1/8 the size) is read too;
* ``voxels/FFFFFF.bin``: the voxelised input scan (occupancy), bit-packed as SemanticKITTI's (or one byte a voxel);
* ``image_00/data_rect/FFFFFF.png``: the left perspective camera, 1408 x 376 (:mod:`distilkit.data.sscbench_camera`);
* ``preprocess/labels/2013_05_28_drive_NNNN_sync/FFFFFF_1_1.npy``: the same target already mapped to train ids
  0..18 with 255 ignored (MonoScene's and VoxFormer's input), read with ``targets: preprocess``.

The target (``preprocess.py``): a voxel is ignored (255) where ``.invalid`` marks it **and** its label is 0 — an
occupied voxel keeps its label even where ``.invalid`` marks it (SemanticKITTI's evaluation drops every invalid
voxel); raw ids the learning map sends to 0 (outlier, bicyclist, motorcyclist, trunk, ...) are ignored too. The grid
lies in the LiDAR frame, as SemanticKITTI's (origin (0, -25.6, -2) m). The folder has no point scans: a sample's
``points`` are the centres of the occupied voxels of ``.bin`` (remission 0), labelled with their voxel's target.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal, Union

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, ssc_lut
from distilkit.data.info import ClassTable, DataInfo
from distilkit.data.kitti_folder import pool_all, pool_labels
from distilkit.data.lidar import LIDAR_INPUTS, LIDAR_TARGETS
from distilkit.data.params import FolderCameraParams, _check_scale
from distilkit.errors import DataError
from distilkit.structures import VoxelGrid

SHAPE = (256, 256, 32)
VOXELS = int(np.prod(SHAPE))
DRIVE = "2013_05_28_drive_{:04d}_sync"
# kitti360.yaml's split (sequence numbers): README: train 8,487 frames, valid 1,812, test 2,566
SPLITS: dict[str, tuple[str, ...]] = {"train": tuple(DRIVE.format(s) for s in (0, 2, 3, 4, 5, 7, 10)),
                                      "valid": (DRIVE.format(6),), "test": (DRIVE.format(9),)}
FRAMES = {"train": 8487, "valid": 1812, "test": 2566}

# kitti360.yaml: learning_map (raw id -> train id), learning_map_inv, and the names of MonoScene's params.py
NAMES: tuple[str, ...] = (
    "empty", "car", "bicycle", "motorcycle", "truck", "other-vehicle", "person", "road", "parking", "sidewalk",
    "other-ground", "building", "fence", "vegetation", "terrain", "pole", "traffic-sign", "other-structure",
    "other-object")
LEARNING_MAP: dict[int, int] = {
    0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 0, 32: 0, 40: 7, 44: 8, 48: 9, 49: 10,
    50: 11, 51: 12, 52: 17, 60: 7, 70: 13, 71: 0, 72: 14, 80: 15, 81: 16, 99: 18, 252: 1, 253: 0, 254: 6, 255: 0,
    256: 5, 257: 5, 258: 4, 259: 5}
LEARNING_MAP_INV: dict[int, int] = {0: 0, 1: 10, 2: 11, 3: 15, 4: 18, 5: 20, 6: 30, 7: 40, 8: 44, 9: 48, 10: 49,
                                    11: 50, 12: 51, 13: 70, 14: 72, 15: 80, 16: 81, 17: 52, 18: 99}
# RGB: kitti360.yaml's color_map (BGR) at each train id's raw id (learning_map_inv)
COLOURS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0), (100, 150, 245), (100, 230, 245), (30, 60, 150), (80, 30, 180), (0, 0, 255), (255, 30, 30),
    (255, 0, 255), (255, 150, 255), (75, 0, 75), (175, 0, 75), (255, 200, 0), (255, 120, 50), (0, 175, 0),
    (150, 240, 80), (255, 240, 150), (255, 0, 0), (255, 150, 0), (50, 255, 255))


def class_table() -> ClassTable:
    """SSCBench-KITTI-360's 19 classes (0 = empty), colours and learning map (``kitti360.yaml``)."""
    return ClassTable(NAMES, COLOURS, dict(LEARNING_MAP), learning_map_inv=dict(LEARNING_MAP_INV))


def drive_name(seq: str) -> str:
    """``"6"``, ``"06"`` or ``"0006"`` -> ``2013_05_28_drive_0006_sync``; a full drive name stays as it is."""
    return DRIVE.format(int(seq)) if seq.isdigit() else seq


def read_voxel_mask(path: str | Path, what: str, shape: tuple[int, int, int] = SHAPE) -> np.ndarray:
    """``.invalid`` / ``.bin`` -> (X, Y, Z) bool: one byte a voxel (SSCBench's ``.invalid``) or bit-packed (the
    size tells which)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    n, size = int(np.prod(shape)), path.stat().st_size
    if size == n // 8:
        return skio.read_voxel_bits(path, shape)
    if size != n:
        raise DataError(f"{path}: {size} bytes, expected {n:,} (one byte a voxel) or {n // 8:,} (bit-packed) for a "
                        f"{' x '.join(map(str, shape))} {what} grid")
    return np.fromfile(path, np.uint8).reshape(shape) > 0


def read_train_ids(path: str | Path, num_classes: int, shape: tuple[int, int, int] = SHAPE) -> np.ndarray:
    """``preprocess/labels/.../FFFFFF_1_1.npy`` (or a prediction in that format) -> (X, Y, Z) uint8 train ids 0..K-1,
    255 ignored (any integer-valued dtype; pickles are refused)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: not a readable .npy array ({exc})") from None
    if arr.shape != shape:
        raise DataError(f"{path}: shape {arr.shape}, expected {shape}")
    ids = arr.astype(np.int64)
    bad = (ids != arr) | ((ids >= num_classes) & (ids != IGNORE_INDEX)) | (ids < 0)
    if bad.any():
        raise DataError(f"{path}: {int(bad.sum())} values are not train ids 0..{num_classes - 1} or 255")
    return ids.astype(np.uint8)


def target(raw: np.ndarray, invalid: np.ndarray, lut: np.ndarray,
           what: str = "labels") -> tuple[np.ndarray, np.ndarray]:
    """(train ids with ignored raw ids 255, the mask the target ignores): ``.invalid`` counts only where the label
    is 0 (``preprocess.py``)."""
    from distilkit.data.classes import remap

    return remap(raw, lut, what).astype(np.uint8), invalid & (raw == 0)


class SscbenchCameraParams(FolderCameraParams):
    """SSCBench-KITTI-360's left perspective camera (``image_00/data_rect/FFFFFF.png``, 1408 x 376), the current
    frame's image only: ``P_rect_00`` and ``calib_cam_to_velo.txt`` where the folder holds KITTI-360's
    ``calibration/``, else the same matrices as SSCBench's MonoScene hard-codes them (kitti_360_dataset.py,
    read_calib); LiDAR -> camera = inv(cam_to_velo) as MonoScene (KITTI-360's convention also applies R_rect_00:
    ``rectify_rotation``); the images resized to ``width`` x ``height`` with the intrinsics; the depth target: the
    occupied voxel centres of .bin projected."""

    height: int = Field(376, ge=8, description="image rows after resizing (SSCBench's images: 376)")
    width: int = Field(1408, ge=8, description="image columns after resizing (SSCBench's images: 1408)")
    rectify_rotation: bool = Field(False, description="also apply perspective.txt's R_rect_00 (KITTI-360's "
                                                      "convention); false: LiDAR -> camera = inv(cam_to_velo), "
                                                      "as SSCBench's MonoScene")

    @field_validator("previous")
    @classmethod
    def _current_only(cls, v: list[int]) -> list[int]:
        if v:
            raise ValueError("previous: SSCBench-KITTI-360's frames are not tied to poses here; only the current "
                             "image is read (previous: [])")
        return v


SplitRef = Union[Literal["train", "valid", "test"], list[str], None]


class SscbenchParams(BaseModel):
    """``sscbench-kitti360``: an SSCBench-KITTI-360 folder, the benchmark's ``KITTI-360`` folder
    (``data_2d_raw/2013_05_28_drive_NNNN_sync/voxels/FFFFFF.label|.invalid|.bin``, ``image_00/data_rect/``,
    ``preprocess/labels/``; dataset/KITTI-360/README.md of ai4ce/SSCBench at commit 9e767e1). Classes:
    dataset/configs/kitti360.yaml, 19 with empty (raw ids as SemanticKITTI's through its learning_map: bicyclist,
    motorcyclist, trunk and outlier ignored, bus and on-rails as other-vehicle, lane-marking as road; colours its BGR
    color_map). Grid: 256 x 256 x 32 voxels at 0.2 m in the LiDAR frame, as SemanticKITTI's. Splits (kitti360.yaml;
    frame counts from the README): train drives 00, 02-05, 07, 10 (8,487 frames), valid 06 (1,812), test 09
    (2,566). Formats (method/MonoScene/monoscene/data/kitti_360/io_data.py): .label uint16 a voxel, .invalid one
    byte a voxel; .bin, "voxelised input" (the README does not say how it is packed), is read bit-packed as
    SemanticKITTI's or one byte a voxel, the size telling which. Target (its preprocess.py): ignored where .invalid
    marks a voxel whose label is 0; occupied voxels keep their label (SemanticKITTI's evaluation drops them). The
    folder has no point scans: points are the occupied voxels of .bin. Licence CC BY-NC-SA 3.0: nothing bundled."""

    model_config = ConfigDict(extra="forbid")
    SPLITS: ClassVar[dict[str, tuple[str, ...]]] = SPLITS
    root: str = Field(..., description="the benchmark's KITTI-360 folder (holds data_2d_raw/ and preprocess/)")
    train: SplitRef = Field("train", description="the drives trained on: train, valid, test, or a list of drive "
                                                 "numbers ('00', '06') or folder names")
    val: SplitRef = Field("valid", description="the drives that select the best checkpoint (none: no validation)")
    test: SplitRef = Field("test", description="the drives scored at the end (the benchmark's test split, drive 09, "
                                               "is labelled; none: the validation split is reported)")
    scale: int = Field(1, description="grid coarsening of the 256x256x32 voxel files (majority pooling)")
    targets: Literal["voxels", "preprocess"] = Field(
        "voxels", description="the target's files: voxels/*.label + .invalid, or preprocess/labels/*_1_1.npy")
    camera: SscbenchCameraParams | None = Field(None, description="also read image_00/data_rect/ and the camera's "
                                                                  "calibration ({} for the defaults); none: no camera")

    _scale = field_validator("scale")(_check_scale)

    @field_validator("train", "val", "test")
    @classmethod
    def _drives(cls, v: Any) -> Any:
        if isinstance(v, list):
            bad = [s for s in v if not (isinstance(s, str) and (s.isdigit() or s.startswith("2013_05_28_drive_")))]
            if bad:
                raise ValueError(f"drives are numbers such as '06' (quoted in YAML) or folder names such as "
                                 f"2013_05_28_drive_0006_sync, got {bad}")
            return v or None
        return v

    def sequences(self, role: str) -> list[str]:
        """The drive folders role ``role`` (train, val, test) reads: [] when the recipe gives it none."""
        ref = getattr(self, role)
        return [] if ref is None else list(SPLITS[ref]) if isinstance(ref, str) else [drive_name(s) for s in ref]

    def table(self) -> ClassTable:
        return class_table()


def sscbench_info(params: SscbenchParams) -> DataInfo:
    """The folder's facts: its class table, its grid at ``scale`` and the camera where asked for."""
    from distilkit.data.camera import CAMERA_FIELDS

    cameras = ()
    if params.camera is not None:
        from distilkit.data.sscbench_camera import describe

        cameras = (describe(params),)
    return DataInfo(VoxelGrid.semantickitti(params.scale), class_table(),
                    fields=LIDAR_INPUTS | LIDAR_TARGETS | (CAMERA_FIELDS if params.camera else frozenset()),
                    cameras=cameras)


def _size_problem(path: Path, sizes: tuple[int, ...], what: str) -> str | None:
    if not path.is_file():
        return f"{path.name}: missing ({what})"
    if path.stat().st_size not in sizes:
        return (f"{path.name}: {path.stat().st_size:,} bytes, expected "
                f"{' or '.join(f'{s:,}' for s in sizes)} ({what} of a 256 x 256 x 32 grid)")
    return None


def frame_problems(root: Path, drive: str, frame: str, p: SscbenchParams) -> list[str]:
    """What one frame lacks or has at the wrong size, each as 'where: what' relative to ``root`` (stat only)."""
    vox = Path("data_2d_raw") / drive / "voxels"
    checks = [(f"{frame}.bin", (VOXELS // 8, VOXELS), "the voxelised input scan")]
    if p.targets == "voxels":
        checks += [(f"{frame}.label", (2 * VOXELS,), "uint16 voxel labels"),
                   (f"{frame}.invalid", (VOXELS, VOXELS // 8), "the invalid mask")]
    out = [f"{vox}/{msg}" for name, sizes, what in checks if (msg := _size_problem(root / vox / name, sizes, what))]
    if p.targets == "preprocess":
        npy = root / "preprocess" / "labels" / drive / f"{frame}_1_1.npy"
        try:
            shape = np.load(npy, mmap_mode="r", allow_pickle=False).shape if npy.is_file() else None
        except (ValueError, OSError):
            shape = "unreadable"
        if shape != SHAPE:
            out.append(f"{npy.relative_to(root)}: " + ("missing (the preprocessed target)" if shape is None else
                                                       f"shape {shape}, expected {SHAPE}"))
    if p.camera is not None:
        image = Path("data_2d_raw") / drive / "image_00" / "data_rect" / f"{frame}.png"
        if not (root / image).is_file():
            out.append(f"{image}: missing (the camera's image)")
    return out


class SscbenchDataset(torch.utils.data.Dataset):
    """An SSCBench-KITTI-360 folder's frames of one role (every frame with a target file of its drives)."""

    def __init__(self, params: SscbenchParams, split: str, what: str | None = None) -> None:
        self.p = params
        self.table = class_table()
        self.lut = ssc_lut(LEARNING_MAP)
        self.root = root = Path(params.root).expanduser()
        drives = params.sequences(split)
        self.items: list[tuple[str, str]] = []
        problems: list[str] = []
        for drive in drives:
            d = root / "data_2d_raw" / drive
            if params.targets == "preprocess":
                frames = sorted(f.name[:-len("_1_1.npy")] for f in
                                (root / "preprocess" / "labels" / drive).glob("*_1_1.npy"))
                where = f"preprocess/labels/{drive}/*_1_1.npy"
            else:
                frames = sorted(f.stem for f in (d / "voxels").glob("*.label"))
                where = f"data_2d_raw/{drive}/voxels/*.label"
            if not d.is_dir():
                problems.append(f"data_2d_raw/{drive}: missing (expected {where} and the voxels/*.bin inputs)")
                continue
            if not frames:
                problems.append(f"{where}: none there")
            for f in frames:
                problems += frame_problems(root, drive, f, params)
            self.items += [(drive, f) for f in frames]
        if problems or not self.items:
            shown = problems[:12] + ([f"... and {len(problems) - 12} more"] if len(problems) > 12 else [])
            raise DataError(f"{root}: {what or f'split {split!r}'} (drives {', '.join(drives) or 'none'}) is not a "
                            "complete SSCBench-KITTI-360 folder:\n  " + "\n  ".join(shown or ["no frames"]))
        self.info = sscbench_info(params)
        self.has_targets = True
        self._grid = VoxelGrid.semantickitti(1)

    def __len__(self) -> int:
        return len(self.items)

    def sample_id(self, i: int) -> str:
        """``<drive>/<frame>``, as the benchmark names its files."""
        return "/".join(self.items[i])

    def dense_target(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(train ids 0..18 with 255, the ignored mask the train ids do not already carry) at full resolution."""
        drive, frame = self.items[i]
        if self.p.targets == "preprocess":
            ids = read_train_ids(self.root / "preprocess" / "labels" / drive / f"{frame}_1_1.npy", len(NAMES))
            return ids, np.zeros(SHAPE, bool)
        vox = self.root / "data_2d_raw" / drive / "voxels"
        raw = skio.read_voxel_labels(vox / f"{frame}.label", SHAPE)
        return target(raw, read_voxel_mask(vox / f"{frame}.invalid", "invalid mask"), self.lut, str(vox))

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        drive, frame = self.items[i]
        labels, invalid = self.dense_target(i)
        occupied = read_voxel_mask(self.root / "data_2d_raw" / drive / "voxels" / f"{frame}.bin", "input")
        idx = np.argwhere(occupied)
        xyz = self._grid.centers(torch.from_numpy(idx)).numpy()
        point_label = labels[occupied]
        points = np.concatenate([xyz, np.zeros((len(xyz), 1), np.float32)], 1).astype(np.float32)
        vl, inv = pool_labels(labels, invalid, self.p.scale, len(NAMES))
        out = {"points": points, "point_frame": np.zeros(len(points), np.uint8),
               "point_label": np.where(point_label == IGNORE_INDEX, 0, point_label).astype(np.uint8),
               "voxel_label": vl.astype(np.uint8), "invalid": pool_all(invalid, self.p.scale)}
        if self.p.camera is not None:
            from distilkit.data.sscbench_camera import camera_fields

            out.update(camera_fields(self.root, drive, frame, self.p.camera, points))
        return out


def sscbench_check(params: SscbenchParams, split: str) -> str | None:
    """What ``distilkit validate`` says of a role's drives: None where they can be read, else every problem (file
    names and sizes only: cheap)."""
    root = Path(params.root).expanduser()
    if not (root / "data_2d_raw").is_dir():
        return (f"{root}: no data_2d_raw/ folder there (an SSCBench-KITTI-360 folder holds data_2d_raw/"
                "2013_05_28_drive_NNNN_sync/voxels/, ...)")
    try:
        SscbenchDataset(params, split)
        if params.camera is not None:  # the calibration files, where the folder has them, must parse
            from distilkit.data.sscbench_camera import calibration

            calibration(root, params.camera.rectify_rotation)
    except DataError as exc:
        return str(exc)
    return None


def sscbench_fingerprint(params: SscbenchParams) -> dict[str, Any]:
    """The parameters but the root, and a digest of the names, sizes and modification times of the files read."""
    import hashlib

    root = Path(params.root).expanduser()
    lines = []
    for drive in sorted({s for role in ("train", "val", "test") for s in params.sequences(role)}):
        folders = [root / "data_2d_raw" / drive / "voxels", root / "preprocess" / "labels" / drive]
        if params.camera is not None:
            folders += [root / "data_2d_raw" / drive / "image_00" / "data_rect", root / "calibration"]
        for f in (f for folder in folders for f in sorted(folder.glob("*"))):
            st = f.stat()
            lines.append(f"{f.relative_to(root).as_posix()} {st.st_size} {st.st_mtime_ns}")
    return {"params": params.model_dump(mode="json", exclude={"root"}, exclude_defaults=True),
            "files": len(lines), "digest": hashlib.sha256("\n".join(lines).encode()).hexdigest()}


__all__ = ["LEARNING_MAP", "NAMES", "SHAPE", "SPLITS", "SscbenchDataset", "SscbenchParams", "class_table",
           "drive_name", "read_train_ids", "read_voxel_mask", "sscbench_check", "sscbench_fingerprint",
           "sscbench_info", "target"]
