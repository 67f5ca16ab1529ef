"""What a dataset tells the rest of a run before any sample is read: its class table, the batch fields
it provides, and where present its voxel grid and cameras. Adapters build themselves from it and
``distilkit validate`` checks recipes against it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

from distilkit.data.classes import (CLASS_COLOURS, CLASS_NAMES, IGNORE_INDEX, LEARNING_MAP, LEARNING_MAP_INV,
                                   POSS_CLASS_COLOURS, POSS_CLASS_NAMES, POSS_LEARNING_MAP, POSS_LEARNING_MAP_INV)
from distilkit.structures import VoxelGrid


@dataclass(frozen=True)
class ClassTable:
    """Train ids 0..K-1 with their names and RGB colours; ``learning_map`` maps the raw label ids of the
    files to train ids; ``ignore_index`` marks voxels or points that are never scored."""

    names: tuple[str, ...]
    colours: tuple[tuple[int, int, int], ...]
    learning_map: Mapping[int, int] = field(default_factory=dict)
    ignore_index: int = IGNORE_INDEX
    learning_map_inv: Mapping[int, int] = field(default_factory=dict)  # train id -> the raw id predictions are written with

    def __post_init__(self) -> None:
        if len(self.colours) != len(self.names):
            raise ValueError(f"ClassTable: {len(self.names)} names but {len(self.colours)} colours")

    @property
    def num_classes(self) -> int:
        return len(self.names)

    @classmethod
    def semantickitti(cls) -> "ClassTable":
        """SemanticKITTI's 20 SSC classes (0 = empty), colours and learning map (semantic-kitti.yaml)."""
        return cls(tuple(CLASS_NAMES), tuple(CLASS_COLOURS), dict(LEARNING_MAP), learning_map_inv=dict(LEARNING_MAP_INV))

    @classmethod
    def semanticposs(cls) -> "ClassTable":
        """SemanticPOSS's 12 SSC classes (0 = empty) and learning map (JS3C-Net's SemanticPOSS.yaml)."""
        return cls(tuple(POSS_CLASS_NAMES), tuple(POSS_CLASS_COLOURS), dict(POSS_LEARNING_MAP),
                   learning_map_inv=dict(POSS_LEARNING_MAP_INV))


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``intrinsics`` 3x3 (pixels), ``lidar_to_camera`` 4x4 (metres), image ``size`` (H, W), and
    the ``frames`` of a sample's images (0 = the current one, -3 = three frames earlier; the batch carries each
    frame's calibration)."""

    name: str
    intrinsics: tuple[tuple[float, ...], ...]
    lidar_to_camera: tuple[tuple[float, ...], ...]
    size: tuple[int, int]
    frames: tuple[int, ...] = (0,)
    depth: str = "dense"  # the depth target: "dense" (rendered; 0 = sky) or "sparse" (LiDAR points; 0 = unknown)


@dataclass(frozen=True)
class FieldGroup:
    """Batch fields a generator makes apart from the rest, with their own code ``version`` and parameters (the
    dataset parameter of the group's name): a stage that reads none of them keeps its identity when they change
    (registered as a dataset's ``field_groups``; the synthetic streets' ``camera``)."""

    fields: frozenset[str]
    version: int = 1


@dataclass(frozen=True)
class DataInfo:
    """The data's facts. ``fields`` names every batch field the dataset's collate provides (inputs and
    targets), which adapters' ``INPUTS`` and terms' batch sources are checked against."""

    grid: VoxelGrid | None
    classes: ClassTable = field(default_factory=ClassTable.semantickitti)
    fields: frozenset[str] = frozenset()
    cameras: tuple[Camera, ...] = ()
    input_frames: int = 1  # scans per sample (LiDAR); 1 for data without a time axis
    point_features: int = 4  # values per input point (x, y, z, intensity)

    @property
    def num_classes(self) -> int:
        return self.classes.num_classes

    @property
    def class_names(self) -> tuple[str, ...]:
        return self.classes.names
