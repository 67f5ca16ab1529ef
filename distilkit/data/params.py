"""Parameters of the built-in datasets (pydantic, validated when a recipe is loaded)."""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal, Union

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


def _previous_field(example: str) -> Any:
    return Field(default_factory=list, description="earlier frames given with the current image, in frames back "
                                                   f"(VoxFormer-T: [12, 9, 6, 3]){example}")


def _distinct_frames(cls: Any, v: list[int]) -> list[int]:
    if len(set(v)) != len(v):
        raise ValueError(f"previous frames must be distinct, got {v}")
    return v


class CameraParams(BaseModel):
    """A pinhole camera mounted like KITTI's left colour camera (cam2: 1241 x 376 pixels, f = 718.9 px, about
    0.27 m ahead of and 0.08 m below the LiDAR), its image scaled to ``width`` x ``height``."""

    model_config = ConfigDict(extra="forbid")
    height: int = Field(48, ge=8, description="image rows (KITTI: 376)")
    width: int = Field(160, ge=8, description="image columns (KITTI: 1241); the focal length scales with it")
    previous: list[Annotated[int, Field(ge=1)]] = _previous_field("; empty: the current image only")
    max_depth: float = Field(80.0, gt=0, description="farther surfaces are sky in the image and 0 in the depth map")
    noise: float = Field(0.02, ge=0, description="std of Gaussian pixel noise (intensities in 0..1)")

    _distinct = field_validator("previous")(classmethod(_distinct_frames))


class FolderCameraParams(BaseModel):
    """A SemanticKITTI folder's left colour camera (``image_2/NNNNNN.png``, calibration ``P2`` and ``Tr`` of
    ``calib.txt``), its images resized to ``width`` x ``height`` (the intrinsics scale with them)."""

    model_config = ConfigDict(extra="forbid")
    height: int = Field(370, ge=8, description="image rows after resizing (KITTI's images: 370 to 376)")
    width: int = Field(1220, ge=8, description="image columns after resizing (KITTI's images: 1226 to 1242)")
    previous: list[Annotated[int, Field(ge=1)]] = _previous_field("; the first frames of a sequence repeat frame 0")
    max_depth: float = Field(80.0, gt=0, description="the depth target: the current scan's points projected into "
                                                     "the image, up to this distance (0 elsewhere)")

    _distinct = field_validator("previous")(classmethod(_distinct_frames))


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


SplitRef = Union[Literal["train", "valid", "test"], list[str], None]
KITTI_SPLITS: dict[str, tuple[str, ...]] = {  # semantic-kitti.yaml (data_metrics.md §1.1)
    "train": ("00", "01", "02", "03", "04", "05", "06", "07", "09", "10"), "valid": ("08",),
    "test": tuple(f"{s:02d}" for s in range(11, 22))}
POSS_SPLITS: dict[str, tuple[str, ...]] = {  # JS3C-Net's SemanticPOSS: 02 is validation and test
    "train": ("00", "01", "03", "04", "05"), "valid": ("02",), "test": ("02",)}
ROLES = ("train", "val", "test")
_LEGACY = {f"{role}_sequences": role for role in ROLES}  # the names of distilkit 0.x


def _split_field(default: Any, what: str) -> Any:
    return Field(default, description=f"{what}: an official split's name (train, valid, test), a list of sequences "
                                      "(['00', '01']) or none")


class SemanticKittiParams(BaseModel):
    """``semantickitti-ssc``: a SemanticKITTI-format folder (``sequences/NN/...``). ``train``, ``val`` and ``test``
    say which sequences each role of a run reads: an official split by name or a list of sequences."""

    model_config = ConfigDict(extra="forbid")
    SPLITS: ClassVar[dict[str, tuple[str, ...]]] = KITTI_SPLITS
    EVERY_SCAN: ClassVar[bool] = False  # True: every stride-th scan is a sample, not only the voxel frames
    root: str = Field(..., description="folder that holds sequences/")
    train: SplitRef = _split_field("train", "the sequences trained on")
    val: SplitRef = _split_field("valid", "the sequences that select the best checkpoint (none: no validation; the "
                                          "last checkpoint is the model)")
    test: SplitRef = _split_field(None, "labelled held-out sequences for test scores (none: the validation split is "
                                        "reported, and says so); sequences without voxel labels (the official test "
                                        "split 11-21) are predicted (publish, `distilkit predict`), never scored")
    scale: int = Field(1, description="grid coarsening of the 256x256x32 voxel files (majority pooling)")
    input_frames: int = Field(1, ge=1, description="scans fused into the input: the current one and the next "
                                                   "input_frames - 1, through the poses")
    stride: int = Field(5, ge=1, description="use every n-th scan (voxel files exist for every 5th)")
    voxels: str = Field("voxels", description="the folder of each sequence the voxel labels are read from "
                                             "(`distilkit data rectify` writes voxels_rectified/); .invalid files "
                                             "always come from voxels/")
    rectify: bool = Field(False, description="SCPNet's label rectification (Algorithm 1) on the fly: voxels of the "
                                             "rectify_classes outside the current scan's instance boxes are ignored")
    rectify_classes: list[str] = Field(
        default_factory=lambda: ["car", "truck", "other-vehicle", "person", "bicyclist", "motorcyclist"],
        description="the dynamic classes rectification cleans (SCPNet's: bicycle and motorcycle stay)")
    camera: FolderCameraParams | None = Field(None, description="also read image_2/ and calib.txt's P2 for camera "
                                                                "models ({} for the defaults); none: LiDAR only")
    occluded: bool = Field(False, description="also read voxels/*.occluded (voxels hidden from the current "
                                              "viewpoint; the official evaluation does not use them) as the target "
                                              "`occluded`")
    scribbles: str | None = Field(None, description="a folder of ScribbleSC's voxel scribbles (Scribble2Scene's "
                                                    "layout: sequences/NN/voxels/NNNNNN.label, raw ids of the "
                                                    "scribbled voxels, 0 elsewhere; relative paths are under root), "
                                                    "read as the target `scribble`; none: no scribbles")
    proposals: str | None = Field(None, description="a folder of VoxFormer's query proposals (its release's layout: "
                                                     "NN/queries/NNNNNN.<tag>, bit-packed 128x128x16 occupancy; "
                                                     "relative paths are under root, e.g. sequences_msnet3d_sweep10), "
                                                     "read as the input `proposal` of a voxformer stage (no stage-1 "
                                                     "model needed); none: no proposals")

    _scale = field_validator("scale")(_check_scale)

    classes: Literal["semantickitti"] = Field("semantickitti", description="the class table of the labels")

    @model_validator(mode="before")
    @classmethod
    def _legacy_names(cls, data: Any) -> Any:
        """``train_sequences``/``val_sequences``/``test_sequences`` (older recipes) are the roles' sequence lists."""
        if isinstance(data, dict) and any(k in data for k in _LEGACY):
            data = dict(data)
            for old, role in _LEGACY.items():
                if old in data:
                    if role in data:
                        raise ValueError(f"{old} and {role} both given: {old} is the older name of {role}")
                    data[role] = data.pop(old) or None
        return data

    @field_validator("train", "val", "test", mode="before")
    @classmethod
    def _sequence_names(cls, v: Any) -> Any:
        """A list of sequences, checked before the split's union is (whose own message would hide the hint)."""
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            raise ValueError(f"sequences are a list such as ['08'] (quoted in YAML) or a split's name (train, valid, "
                             f"test), got {v!r}")
        if isinstance(v, list):
            bad = [s for s in v if not (isinstance(s, str) and s.isdigit())]
            if bad:
                raise ValueError(f"sequence names are digit strings such as '00' or '08' (quote them in YAML), "
                                 f"got {bad}")
            return v or None
        return v

    @model_validator(mode="after")
    def _known_classes(self) -> "SemanticKittiParams":
        from distilkit.data.rectify import dynamic_ids

        dynamic_ids(self.rectify_classes, self.table().names)
        if self.train is None:
            raise ValueError("train: none given (an official split's name or a list of sequences)")
        return self

    def sequences(self, role: str) -> list[str]:
        """The sequences role ``role`` (train, val, test) reads: [] when the recipe gives it none."""
        ref = getattr(self, role)
        return [] if ref is None else list(self.SPLITS[ref]) if isinstance(ref, str) else list(ref)

    def for_submission(self, root: str, test: str | list[str]) -> "SemanticKittiParams":
        """These parameters reading ``test`` (an official split's name or sequences) of the folder at ``root`` as the
        benchmark scores it: the voxel frames, as labelled (no rectification; no .occluded needed)."""
        return type(self)(**{**self.model_dump(exclude={"test"}), "root": root, "test": test, "rectify": False,
                             "occluded": False, "scribbles": None})

    def table(self) -> Any:
        """The :class:`~distilkit.data.info.ClassTable` of the labels."""
        from distilkit.data.info import ClassTable

        return ClassTable.semanticposs() if self.classes == "semanticposs" else ClassTable.semantickitti()


class SemanticKittiScanParams(SemanticKittiParams):
    """``semantickitti-scan``: every scan of the folder with its point labels (fused with the next ``input_frames``
    - 1 through the poses); the voxel targets of the frames that have them (every 5th), ignored on the others."""

    EVERY_SCAN: ClassVar[bool] = True
    stride: int = Field(1, ge=1, description="use every n-th scan (1: all of them)")

    def for_submission(self, root: str, test: str | list[str]) -> SemanticKittiParams:
        """A model trained on every scan predicts the benchmark's frames (the every-5th voxel frames) like the others."""
        ssc = SemanticKittiParams(**self.model_dump(exclude={"stride", "test"}))
        return ssc.for_submission(root, test)


class SemanticPossParams(SemanticKittiParams):
    """``semanticposs-ssc``: a SemanticPOSS folder in SemanticKITTI's layout with JS3C-Net's completion labels (11
    classes + empty on the same 256 x 256 x 32 grid; data_metrics.md §6). Official splits: train 00, 01, 03, 04, 05;
    valid (and test) 02."""

    SPLITS: ClassVar[dict[str, tuple[str, ...]]] = POSS_SPLITS
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
    gt_voxel: float = Field(0.2, gt=0, description="the map keeps one original point per voxel of this size "
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
