"""SSCBench-KITTI-360 (Li et al., SSCBench, IROS 2024): its folder layout, file formats, class table and splits, and
the dataset's parameters (``sscbench-kitti360``; the folder read and checked as a dataset is
:mod:`distilkit.data.sscbench_folder`'s). Facts from ai4ce/SSCBench at commit 9e767e1 (2025-04-09):
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

A drive's frames are its ``voxels/*.bin``, as the benchmark's loader lists them (a frame with a target but no
``.bin`` is left out: :mod:`distilkit.data.sscbench_folder`). Frame counts: the README says train 8,487, valid
1,812, test 2,566; the release holds train 8,483 and test 2,165 (the maintainers' answer in issue #23, 2025-04-06;
the valid count is not restated there).

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
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX
from distilkit.data.info import ClassTable, DataInfo
from distilkit.data.lidar import LIDAR_INPUTS, LIDAR_TARGETS
from distilkit.data.params import FolderCameraParams, _check_scale
from distilkit.errors import DataError
from distilkit.structures import VoxelGrid

SHAPE = (256, 256, 32)
VOXELS = int(np.prod(SHAPE))
DRIVE = "2013_05_28_drive_{:04d}_sync"
# kitti360.yaml's split (sequence numbers)
SPLITS: dict[str, tuple[str, ...]] = {"train": tuple(DRIVE.format(s) for s in (0, 2, 3, 4, 5, 7, 10)),
                                      "valid": (DRIVE.format(6),), "test": (DRIVE.format(9),)}
# frames a split holds: as dataset/KITTI-360/README.md (at 9e767e1) says, and as the release holds them (ai4ce/SSCBench
# issue #23, the maintainers' answer of 2025-04-06: 8,483 in the training drives' voxels/, 2,165 in the test drive's;
# drive 0003's preprocess/labels/ has four label-only frames more, 000970-000985, which the loader leaves out)
README_FRAMES = {"train": 8487, "valid": 1812, "test": 2566}
RELEASE_FRAMES = {"train": 8483, "test": 2165}

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


def dtype_problem(dtype: np.dtype, num_classes: int) -> str | None:
    """Why an array of ``dtype`` cannot hold train ids (a bool array is not class ids), or None: integers, or floats
    holding whole numbers (``preprocess.py`` saves float32)."""
    if dtype.kind == "b":
        return (f"a bool array, not class ids (train ids 0..{num_classes - 1}, 255 ignored, in an integer or float "
                "dtype)")
    if dtype.kind not in "iuf":
        return f"a {dtype} array, not class ids (train ids 0..{num_classes - 1}, 255 ignored)"
    return None


def read_train_ids(path: str | Path, num_classes: int, shape: tuple[int, int, int] = SHAPE) -> np.ndarray:
    """``preprocess/labels/.../FFFFFF_1_1.npy`` (or a prediction in that format) -> (X, Y, Z) uint8 train ids 0..K-1,
    255 ignored (integers, or floats holding whole numbers; bool arrays and pickles are refused)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DataError(f"{path}: not a readable .npy array ({exc})") from None
    if arr.shape != shape:
        raise DataError(f"{path}: shape {arr.shape}, expected {shape}")
    kind_problem = dtype_problem(arr.dtype, num_classes)
    if kind_problem:
        raise DataError(f"{path}: {kind_problem}")
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

    return remap(raw, lut, what, "SSCBench-KITTI-360").astype(np.uint8), invalid & (raw == 0)


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
    color_map). Grid: 256 x 256 x 32 voxels at 0.2 m in the LiDAR frame, as SemanticKITTI's. Splits (kitti360.yaml):
    train drives 00, 02-05, 07, 10, valid 06, test 09; the release holds 8,483 training frames and 2,165 test frames
    (ai4ce/SSCBench issue #23; its README says train 8,487, valid 1,812, test 2,566). A drive's frames are its
    voxels/*.bin, as the benchmark's loader (method/MonoScene/monoscene/data/kitti_360/kitti_360_dataset.py) lists
    them: a frame with a target but no .bin (the release's drive 0003 has four in preprocess/labels/, 000970-000985)
    is left out and counted in a note. A drive is read once; a validation drive is not a training drive. Formats
    (method/MonoScene/monoscene/data/kitti_360/io_data.py): .label uint16 a voxel, .invalid one byte a voxel; .bin,
    "voxelised input" (the README does not say how it is packed), is read bit-packed as SemanticKITTI's or one byte a
    voxel, the size telling which. Target (its preprocess.py): ignored where .invalid
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

    @field_validator("train", "val", "test", mode="before")
    @classmethod
    def _drives(cls, v: Any) -> Any:
        """A list of drives, checked before the split's union is (whose own message would hide the hint)."""
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            raise ValueError(f"drives are a list such as ['06'] (numbers quoted in YAML) or a split's name (train, "
                             f"valid, test), got {v!r}")
        if isinstance(v, list):
            bad = [s for s in v if not (isinstance(s, str) and (s.isdigit() or s.startswith("2013_05_28_drive_")))]
            if bad:
                raise ValueError(f"drives are numbers such as '06' (quoted in YAML: an unquoted 06 is the number 6) "
                                 f"or folder names such as 2013_05_28_drive_0006_sync, got {bad}")
            return v or None
        return v

    @model_validator(mode="after")
    def _distinct_drives(self) -> "SscbenchParams":
        """Drives to train on; none read twice by a role; no validation drive trained on."""
        if self.train is None:
            raise ValueError("train: none given (an official split's name, e.g. train, or a list of drives, e.g. "
                             "['00', '02'])")
        for role in ("train", "val", "test"):
            drives = self.sequences(role)
            twice = sorted({d for d in drives if drives.count(d) > 1})
            if twice:
                raise ValueError(f"{role}: {', '.join(twice)} given twice (a drive is read once)")
        trained = set(self.sequences("train"))
        both = [d for d in self.sequences("val") if d in trained]
        if both:
            raise ValueError(f"val: {', '.join(both)} is also a training drive (the best checkpoint would be chosen "
                             "on frames it trained on; val: null trains without validation)")
        return self

    def sequences(self, role: str) -> list[str]:
        """The drive folders role ``role`` (train, val, test) reads: [] when the recipe gives it none."""
        ref = getattr(self, role)
        return [] if ref is None else list(SPLITS[ref]) if isinstance(ref, str) else [drive_name(s) for s in ref]

    def table(self) -> ClassTable:
        return class_table()

    def for_submission(self, root: str, test: str | list[str]) -> "SscbenchParams":
        """These parameters reading ``test`` (a split's name or drives) of the folder at ``root``, for ``predict``."""
        return type(self)(**{**self.model_dump(exclude={"root", "test"}), "root": root, "test": test})


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


__all__ = ["LEARNING_MAP", "NAMES", "README_FRAMES", "RELEASE_FRAMES", "SHAPE", "SPLITS", "SscbenchParams", "VOXELS",
           "class_table", "drive_name", "dtype_problem", "read_train_ids", "read_voxel_mask", "sscbench_info", "target"]
