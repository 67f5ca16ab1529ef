"""Registered datasets: the synthetic LiDAR scenes and SemanticKITTI-format folders.

Both give LiDAR samples (:mod:`distilkit.data.lidar`) and register :func:`~distilkit.data.lidar.collate_lidar`
as their collate; their :class:`~distilkit.data.info.DataInfo` names the fields it provides.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from distilkit.data.batch import Batch
from distilkit.data.camera import CAMERA_FIELDS, add_camera, rig
from distilkit.data.info import DataInfo, FieldGroup
from distilkit.data.kitti_folder import SemanticKittiDataset, kitti_check, kitti_fingerprint, kitti_info
from distilkit.data.lidar import LIDAR_INPUTS, LIDAR_TARGETS, collate_lidar
from distilkit.data.params import (SceneParams, SemanticKittiParams, SemanticKittiScanParams, SemanticPossParams,
                                   SyntheticParams)
from distilkit.data.probe import cloud_plan, grid_plan
from distilkit.data.render import CAMERA_VERSION
from distilkit.data.sscbench import SscbenchParams, sscbench_info
from distilkit.data.sscbench_folder import sscbench_check, sscbench_fingerprint, sscbench_notes
from distilkit.data.synthetic import GENERATOR_VERSION
from distilkit.structures import VoxelGrid
from distilkit.registry import DATASETS


class ArrayDataset(torch.utils.data.Dataset):
    """Samples held as stacked arrays with point offsets (what the synthetic cache stores)."""

    def __init__(self, arrays: dict[str, np.ndarray], info: DataInfo) -> None:
        self.a = arrays
        self.info = info

    def __len__(self) -> int:
        return len(self.a["offsets"]) - 1

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        lo, hi = int(self.a["offsets"][i]), int(self.a["offsets"][i + 1])
        return {
            "points": self.a["points"][lo:hi],
            "point_frame": self.a["point_frame"][lo:hi],
            "point_label": self.a["point_label"][lo:hi],
            "voxel_label": self.a["voxel_label"][i],
            "invalid": self.a["invalid"][i],
            **({"scribble": self.a["scribble"][i]} if "scribble" in self.a else {}),
            **{k: self.a[k][i] for k in CAMERA_FIELDS if k in self.a},  # the camera's arrays bear its fields' names
        }


def build_synthetic(params: SyntheticParams, split: str,
                    progress: Callable[[int, int], None] | None = None) -> ArrayDataset:
    from distilkit.data.synthetic import generate_split

    count = {"train": params.num_train, "val": params.num_val, "test": params.num_test}[split]
    arrays = generate_split(params, split, count, progress)
    if params.camera is not None:
        from distilkit.data.render import generate_camera_split

        arrays = {**arrays, **generate_camera_split(params, split, count, progress)}
    return ArrayDataset(arrays, synthetic_info(params))


def synthetic_info(params: SyntheticParams) -> DataInfo:
    camera = params.camera is not None
    return DataInfo(VoxelGrid.semantickitti(params.scale),
                    fields=LIDAR_INPUTS | LIDAR_TARGETS | {"scribble"} | (CAMERA_FIELDS if camera else frozenset()),
                    cameras=(rig(params.camera, params.ego_speed),) if params.camera is not None else (),
                    input_frames=params.input_frames)


def collate_street(samples: list[dict[str, np.ndarray]]) -> Batch:
    """A synthetic street's batch: the LiDAR fields, and the camera's where the data renders them."""
    return add_camera(collate_lidar(samples), samples)


def _synthetic_factory(params: SyntheticParams, split: str, progress: Any = None) -> ArrayDataset:
    return build_synthetic(params, split, progress)


def _kitti_factory(params: SemanticKittiParams, split: str, progress: Any = None) -> SemanticKittiDataset:
    return SemanticKittiDataset(params, split)


DATASETS.add(
    "synthetic-lidar", _synthetic_factory,
    description="procedural street scenes, ray-cast LiDAR scans, multi-frame input, SSC ground truth and scribbles; "
                "with `camera` also a KITTI-like camera's images, depth and calibration (cached on disk)",
    paper="distilkit (SemanticKITTI conventions, Behley et al. ICCV 2019)",
    params=SyntheticParams, info=synthetic_info, collate=collate_street, version=GENERATOR_VERSION,
    has_split=lambda p, split: True, probe=grid_plan,
    field_groups={"camera": FieldGroup(CAMERA_FIELDS, CAMERA_VERSION)},
)
for _name, _params, _description, _paper in (
        ("semantickitti", SemanticKittiParams, "a SemanticKITTI-format folder: velodyne/, labels/, "
         "voxels/*.label|.invalid (|.occluded), poses.txt, calib.txt (scans fused through the poses, SSC targets); "
         "with `camera` also image_2/ and P2 (the camera batch fields, sparse LiDAR depth)",
         "Behley et al., SemanticKITTI, ICCV 2019"),
        ("semantickitti-ssc", SemanticKittiParams, "the same as semantickitti (the name the SSC benchmark goes by)",
         "Behley et al., SemanticKITTI, ICCV 2019"),
        ("semantickitti-scan", SemanticKittiScanParams, "every scan of a SemanticKITTI folder (stride 1) with its "
         "point labels, fused with the next input_frames - 1 scans through the poses (SCPNet's multi-frame teacher); "
         "the voxel targets of the labelled every-5th frames, ignored on the others",
         "Behley et al., SemanticKITTI, ICCV 2019; Xia et al., SCPNet, CVPR 2023"),
        ("semanticposs-ssc", SemanticPossParams, "a SemanticPOSS folder in SemanticKITTI's layout with JS3C-Net's "
         "completion labels: 11 classes + empty, train 00/01/03/04/05, valid 02", "Pan et al., SemanticPOSS, IV "
         "2020; completion labels: Yan et al., JS3C-Net, AAAI 2021")):
    DATASETS.add(_name, _kitti_factory, description=_description, paper=_paper, params=_params,
                 info=kitti_info, collate=collate_street, version=1,
                 has_split=lambda p, split: bool(p.sequences(split)), probe=grid_plan,
                 fingerprint=kitti_fingerprint, check=kitti_check)


def _sscbench_factory(params: Any, split: str, progress: Any = None) -> Any:
    from distilkit.data.sscbench_folder import SscbenchDataset

    return SscbenchDataset(params, split)


DATASETS.add(
    "sscbench-kitti360", _sscbench_factory,
    description="an SSCBench-KITTI-360 folder: data_2d_raw/2013_05_28_drive_NNNN_sync/voxels/*.label|.invalid|.bin "
                "(or preprocess/labels/*_1_1.npy), 19 classes, train 00/02-05/07/10, valid 06, test 09; the input "
                "is the voxelised scan; with `camera` also image_00/data_rect/ and its calibration",
    paper="Li et al., SSCBench, IROS 2024 (ai4ce/SSCBench, dataset/configs/kitti360.yaml)",
    params=SscbenchParams, info=sscbench_info, collate=collate_street, version=1,
    has_split=lambda p, split: bool(p.sequences(split)), probe=grid_plan,
    fingerprint=sscbench_fingerprint, check=sscbench_check, notes=sscbench_notes)


def _scenes_factory(params: Any, split: str, progress: Any = None) -> Any:
    from distilkit.data.scenes import build_scenes

    return build_scenes(params, split, progress)


def _scenes_info(params: Any) -> DataInfo:
    from distilkit.data.scenes import scenes_info

    return scenes_info(params)


def _collate_scenes(samples: list[dict[str, Any]]) -> Any:
    from distilkit.data.scenes import collate_scenes

    return collate_scenes(samples)


DATASETS.add(
    "synthetic-scenes", _scenes_factory,
    description="partial scan / dense static scene pairs from the synthetic streets, as LiDiff trains on them "
                "(padded point clouds; cached on disk)",
    paper="Nunes et al., LiDiff, CVPR 2024 (data pipeline); distilkit synthetic streets",
    params=SceneParams, info=_scenes_info, collate=_collate_scenes, version=1,
    has_split=lambda p, split: True, probe=cloud_plan,
)
