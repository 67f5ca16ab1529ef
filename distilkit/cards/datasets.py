"""The datasets' declarations (torch-free): the synthetic LiDAR scenes, the SemanticKITTI-format folders, the
SSCBench-KITTI-360 folder and the synthetic scene pairs, with everything checking a recipe and a stage's identity
read of them (their parameters, :class:`~distilkit.data.info.DataInfo`, splits, checks, notes, fingerprints, code
versions and field groups). The builders (:mod:`distilkit.data.datasets`), collates and memory probes are imported
the first time a run uses them."""

from __future__ import annotations

from typing import Any

from distilkit.data.camera import CAMERA_FIELDS
from distilkit.data.facts import scenes_info, synthetic_info
from distilkit.data.info import FieldGroup
from distilkit.data.kitti_listing import kitti_check, kitti_fingerprint, kitti_info
from distilkit.data.params import (SceneParams, SemanticKittiParams, SemanticKittiScanParams, SemanticPossParams,
                                   SyntheticParams)
from distilkit.data.render import CAMERA_VERSION
from distilkit.data.sscbench import SscbenchParams, sscbench_info
from distilkit.data.sscbench_listing import sscbench_check, sscbench_fingerprint, sscbench_notes
from distilkit.data.synthetic import GENERATOR_VERSION
from distilkit.registry import DATASETS, lazy

_IMPL = "distilkit.data.datasets"
COLLATE_STREET = lazy(f"{_IMPL}:collate_street")  # the LiDAR fields, and the camera's where the data has them


def every_split(params: Any, split: str) -> bool:
    """A generated dataset has every split."""
    return True


def listed_split(params: Any, split: str) -> bool:
    """A folder has the splits its parameters list sequences (drives) for."""
    return bool(params.sequences(split))


DATASETS.declare(
    "synthetic-lidar", f"{_IMPL}:_synthetic_factory", card=None,
    description="procedural street scenes, ray-cast LiDAR scans, multi-frame input, SSC ground truth and scribbles; "
                "with `camera` also a KITTI-like camera's images, depth and calibration (cached on disk)",
    paper="distilkit (SemanticKITTI conventions, Behley et al. ICCV 2019)",
    params=SyntheticParams, info=synthetic_info, collate=COLLATE_STREET, version=GENERATOR_VERSION,
    has_split=every_split, probe=lazy("distilkit.data.probe:grid_plan"),
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
    DATASETS.declare(_name, f"{_IMPL}:_kitti_factory", card=None, description=_description, paper=_paper,
                     params=_params, info=kitti_info, collate=COLLATE_STREET, version=1,
                     has_split=listed_split, probe=lazy("distilkit.data.probe:grid_plan"),
                     fingerprint=kitti_fingerprint, check=kitti_check)

DATASETS.declare(
    "sscbench-kitti360", f"{_IMPL}:_sscbench_factory", card=None,
    description="an SSCBench-KITTI-360 folder: data_2d_raw/2013_05_28_drive_NNNN_sync/voxels/*.label|.invalid|.bin "
                "(or preprocess/labels/*_1_1.npy), 19 classes, train 00/02-05/07/10, valid 06, test 09; the input "
                "is the voxelised scan; with `camera` also image_00/data_rect/ and its calibration",
    paper="Li et al., SSCBench, IROS 2024 (ai4ce/SSCBench, dataset/configs/kitti360.yaml)",
    params=SscbenchParams, info=sscbench_info, collate=COLLATE_STREET, version=1,
    has_split=listed_split, probe=lazy("distilkit.data.probe:grid_plan"),
    fingerprint=sscbench_fingerprint, check=sscbench_check, notes=sscbench_notes)

DATASETS.declare(
    "synthetic-scenes", f"{_IMPL}:_scenes_factory", card=None,
    description="partial scan / dense static scene pairs from the synthetic streets, as LiDiff trains on them "
                "(padded point clouds; cached on disk)",
    paper="Nunes et al., LiDiff, CVPR 2024 (data pipeline); distilkit synthetic streets",
    params=SceneParams, info=scenes_info, collate=lazy("distilkit.data.scenes:collate_scenes"), version=1,
    has_split=every_split, probe=lazy("distilkit.data.probe:cloud_plan"),
)

__all__ = ["every_split", "listed_split"]
