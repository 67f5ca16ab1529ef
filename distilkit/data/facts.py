"""What the synthetic datasets tell before generating anything: their :class:`~distilkit.data.info.DataInfo` (the
grid, classes, batch fields and cameras their parameters give). Torch-free and without generating a sample:
``distilkit validate --static`` reads it; :mod:`distilkit.data.datasets` and :mod:`distilkit.data.scenes` build the
data."""

from __future__ import annotations

from distilkit.data.camera import CAMERA_FIELDS, rig
from distilkit.data.info import ClassTable, DataInfo
from distilkit.data.lidar import LIDAR_INPUTS, LIDAR_TARGETS
from distilkit.data.params import SceneParams, SyntheticParams
from distilkit.structures import VoxelGrid

SCENE_FIELDS = frozenset({"scan", "scan_lengths", "scene", "scene_lengths", "scene_eval", "scene_eval_lengths"})


def synthetic_info(params: SyntheticParams) -> DataInfo:
    camera = params.camera is not None
    return DataInfo(VoxelGrid.semantickitti(params.scale),
                    fields=LIDAR_INPUTS | LIDAR_TARGETS | {"scribble"} | (CAMERA_FIELDS if camera else frozenset()),
                    cameras=(rig(params.camera, params.ego_speed),) if params.camera is not None else (),
                    input_frames=params.input_frames)


def scenes_info(params: SceneParams) -> DataInfo:
    return DataInfo(None, ClassTable(("scene",), ((160, 160, 160),)), SCENE_FIELDS)


__all__ = ["SCENE_FIELDS", "scenes_info", "synthetic_info"]
