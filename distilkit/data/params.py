"""Parameters of the built-in datasets (pydantic, validated when a recipe is loaded)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

SCALES = (1, 2, 4, 8)


def _check_scale(v: int) -> int:
    if v not in SCALES:
        raise ValueError(f"scale must be one of {SCALES} (256x256x32 divided by it), got {v}")
    return v


class _SensorParams(BaseModel):
    """The simulated LiDAR and drive shared by the synthetic data sets (a Velodyne HDL-64-like sensor, 32 beams)."""

    beams: int = Field(32, ge=2)
    fov_up: float = 2.0
    fov_down: float = -24.8
    range_noise: float = Field(0.02, ge=0, description="std of Gaussian range noise, metres")
    ego_speed: float = Field(1.0, ge=0, description="metres per frame (KITTI: about 1 m at 10 Hz)")


class CameraParams(BaseModel):
    """A pinhole camera mounted like KITTI's left colour camera (cam2: 1241 x 376 pixels, f = 718.9 px, about
    0.27 m ahead of and 0.08 m below the LiDAR), its image scaled to ``width`` x ``height``."""

    model_config = ConfigDict(extra="forbid")
    height: int = Field(48, ge=8, description="image rows (KITTI: 376)")
    width: int = Field(160, ge=8, description="image columns (KITTI: 1241); the focal length scales with it")
    previous: list[Annotated[int, Field(ge=1)]] = Field(
        default_factory=list, description="earlier frames given with the current image, in frames back "
                                          "(VoxFormer-T: [12, 9, 6, 3]); empty: the current image only")
    max_depth: float = Field(80.0, gt=0, description="farther surfaces are sky in the image and 0 in the depth map")
    noise: float = Field(0.02, ge=0, description="std of Gaussian pixel noise (intensities in 0..1)")

    @field_validator("previous")
    @classmethod
    def _distinct(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"previous frames must be distinct, got {v}")
        return v


class SyntheticParams(_SensorParams):
    """``synthetic-lidar``: procedural street scenes cast with a spinning LiDAR."""

    model_config = ConfigDict(extra="forbid")
    seed: int = Field(0, description="scene seed (independent of the training seed)")
    scale: int = Field(4, description="grid coarsening: 1 = 256x256x32 at 0.2 m, 4 = 64x64x8 at 0.8 m")
    num_train: int = Field(16, ge=1)
    num_val: int = Field(16, ge=1, description="validation scenes (select the best checkpoint)")
    num_test: int = Field(32, ge=1, description="test scenes (scores reported at the best and the last checkpoint)")
    input_frames: int = Field(5, ge=1, description="frames fused into the input (current + next T-1)")
    gt_frames: int = Field(10, ge=0, description="future scans voxelised with the current one for the SSC target")
    azimuth_steps: int = Field(1024, ge=8)
    max_range: float = Field(60.0, gt=0)
    scribble: Literal["lines", "random"] = Field(
        "lines", description="scribble labels: BEV line scribbles (ScribbleKITTI) or a random subset of points")
    scribble_spacing: float = Field(7.5, gt=0, description="metres between parallel scribble lines")
    scribble_width: float = Field(0.3, gt=0, description="width of a scribble line, metres")
    scribble_fraction: float = Field(0.1, gt=0, le=1, description="share of points labelled with scribble: random")
    camera: CameraParams | None = Field(None, description="also render camera images of the same streets "
                                                          "({} for the defaults); none: LiDAR only")

    _scale = field_validator("scale")(_check_scale)


class SemanticKittiParams(BaseModel):
    """``semantickitti``: a SemanticKITTI-format folder (``sequences/NN/...``)."""

    model_config = ConfigDict(extra="forbid")
    root: str = Field(..., description="folder that holds sequences/")
    train_sequences: list[str] = ["00", "01", "02", "03", "04", "05", "06", "07", "09", "10"]
    val_sequences: list[str] = ["08"]
    test_sequences: list[str] = Field(default_factory=list, description="labelled held-out sequences for test "
                                      "scores (none: the validation split is reported, and says so)")
    scale: int = Field(1, description="grid coarsening of the 256x256x32 voxel files (majority pooling)")
    input_frames: int = Field(1, ge=1)
    stride: int = Field(5, ge=1, description="use every n-th scan (voxel files exist for every 5th)")
    voxels: str = Field("voxels", description="the folder of each sequence the voxel labels are read from "
                                             "(`distilkit data rectify` writes voxels_rectified/); .invalid files "
                                             "always come from voxels/")
    rectify: bool = Field(False, description="SCPNet's label rectification (Algorithm 1) on the fly: voxels of the "
                                             "rectify_classes outside the current scan's instance boxes are ignored")
    rectify_classes: list[str] = Field(
        default_factory=lambda: ["car", "truck", "other-vehicle", "person", "bicyclist", "motorcyclist"],
        description="the dynamic classes rectification cleans (SCPNet's: bicycle and motorcycle stay)")

    _scale = field_validator("scale")(_check_scale)

    classes: Literal["semantickitti"] = Field("semantickitti", description="the class table of the labels")

    @model_validator(mode="after")
    def _known_classes(self) -> "SemanticKittiParams":
        from distilkit.data.rectify import dynamic_ids

        dynamic_ids(self.rectify_classes, self.table().names)
        return self

    def table(self) -> Any:
        """The :class:`~distilkit.data.info.ClassTable` of the labels."""
        from distilkit.data.info import ClassTable

        return ClassTable.semanticposs() if self.classes == "semanticposs" else ClassTable.semantickitti()


class SemanticPossParams(SemanticKittiParams):
    """``semanticposs-ssc``: a SemanticPOSS folder in SemanticKITTI's layout with JS3C-Net's completion labels (11
    classes + empty on the same 256 x 256 x 32 grid; data_metrics.md §6)."""

    train_sequences: list[str] = ["00", "01", "03", "04", "05"]
    val_sequences: list[str] = ["02"]
    rectify_classes: list[str] = Field(default_factory=lambda: ["people", "rider", "car"],
                                       description="the dynamic classes rectification cleans (POSS_DYNAMIC)")
    classes: Literal["semanticposs"] = Field("semanticposs", description="the class table of the labels")


class SceneParams(_SensorParams):
    """``synthetic-scenes``: scan / dense scene pairs from the synthetic streets, as LiDiff trains on them."""

    model_config = ConfigDict(extra="forbid")
    seed: int = Field(0, description="scene seed (independent of the training seed)")
    num_train: int = Field(8, ge=1)
    num_val: int = Field(4, ge=1)
    num_test: int = Field(8, ge=1)
    scan_points: int = Field(1024, ge=8, description="points of the partial scan after farthest-point sampling "
                                                     "(LiDiff: 18,000)")
    scene_points: int = Field(10240, ge=8, description="points of the dense ground-truth scene (LiDiff: 180,000 = "
                                                       "10 x the scan)")
    frames: int = Field(11, ge=1, description="scans accumulated into the scene (the current one in the middle)")
    gt_voxel: float = Field(0.2, gt=0, description="the scene keeps one point (the mean) per voxel of this size "
                                                   "(LiDiff's maps: 0.1 m)")
    viewpoint_voxel: float = Field(10.0, gt=0, description="scene points are kept in cells of this size that hold "
                                                           "a scan point (LiDiff: 10 m)")
    min_range: float = Field(3.5, ge=0, description="scan points closer than this are dropped (LiDiff: 3.5 m)")
    max_range: float = Field(50.0, gt=0, description="scan and scene range (LiDiff: 50 m)")
    min_z: float = Field(-4.0, description="points below this height are dropped (LiDiff: -4 m)")
    azimuth_steps: int = Field(768, ge=8)

    @model_validator(mode="after")
    def _whole_copies(self) -> "SceneParams":
        if self.scene_points % self.scan_points:
            raise ValueError(f"scene_points ({self.scene_points}) must be a multiple of scan_points "
                             f"({self.scan_points}): LiDiff starts from the scan duplicated scene/scan times")
        return self
