"""The datasets' builders: the synthetic LiDAR scenes and SemanticKITTI-format folders (and the builders of the
SSCBench-KITTI-360 folder and the synthetic scene pairs), each imported the first time a run builds its data.
:mod:`distilkit.cards.datasets` declares them with what checking a recipe reads (their parameters, their
:class:`~distilkit.data.info.DataInfo`, checks and fingerprints: torch-free).

All but ``synthetic-scenes`` give LiDAR samples (:mod:`distilkit.data.lidar`) and are declared with
:func:`collate_street` (:func:`~distilkit.data.lidar.collate_lidar` and the camera's fields) as their collate; their
:class:`~distilkit.data.info.DataInfo` names the fields it provides.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from distilkit.data.batch import Batch
from distilkit.data.camera import CAMERA_FIELDS, add_camera
from distilkit.data.facts import synthetic_info
from distilkit.data.info import DataInfo
from distilkit.data.kitti_folder import SemanticKittiDataset
from distilkit.data.lidar import collate_lidar
from distilkit.data.params import SemanticKittiParams, SyntheticParams


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


def collate_street(samples: list[dict[str, np.ndarray]]) -> Batch:
    """A synthetic street's batch: the LiDAR fields, and the camera's where the data renders them."""
    return add_camera(collate_lidar(samples), samples)


def _synthetic_factory(params: SyntheticParams, split: str, progress: Any = None) -> ArrayDataset:
    return build_synthetic(params, split, progress)


def _kitti_factory(params: SemanticKittiParams, split: str, progress: Any = None) -> SemanticKittiDataset:
    return SemanticKittiDataset(params, split)


def _sscbench_factory(params: Any, split: str, progress: Any = None) -> Any:
    from distilkit.data.sscbench_folder import SscbenchDataset

    return SscbenchDataset(params, split)


def _scenes_factory(params: Any, split: str, progress: Any = None) -> Any:
    from distilkit.data.scenes import build_scenes

    return build_scenes(params, split, progress)


__all__ = ["ArrayDataset", "build_synthetic", "collate_street", "synthetic_info"]
