"""LiDAR samples and their batch: what the synthetic scenes and SemanticKITTI folders share.

A sample is a dict of numpy arrays:

* ``points`` (M,4) x, y, z, intensity in the current sensor frame; ``point_frame`` (M,) frame
  offset (0 = current scan); ``point_label`` (M,) segmentation train id (0 = unlabelled);
* ``voxel_label`` (X,Y,Z) SSC train ids (0 = empty, 255 = ignore); ``invalid`` (X,Y,Z) bool;
* optionally ``scribble`` (X,Y,Z) ScribbleSC labels (0 empty, 1-19, 254 unlabelled, 255 invalid), ``occluded``
  (X,Y,Z) bool (SemanticKITTI's ``.occluded``: hidden from the current viewpoint) and ``proposal`` (X/2,Y/2,Z/2)
  uint8, VoxFormer's query proposals read from a folder (an input).

:func:`collate_lidar` concatenates points with a ``point_batch`` index (inputs) and stacks the grids
(targets), adding ``voxel_target`` = ``voxel_label`` with invalid voxels set to 255 (the training target).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import BaseModel

from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX
from distilkit.data.info import DataInfo

LIDAR_INPUTS = frozenset({"points", "point_batch", "point_frame"})
LIDAR_TARGETS = frozenset({"point_label", "voxel_label", "invalid", "voxel_target"})


def collate_lidar(samples: list[dict[str, np.ndarray]]) -> Batch:
    """Concatenate points (with ``point_batch``) into inputs and stack voxel grids into targets."""
    import torch

    pts = [torch.from_numpy(np.ascontiguousarray(s["points"], dtype=np.float32)) for s in samples]
    inputs = {
        "points": torch.cat(pts),
        "point_batch": torch.cat([torch.full((len(p),), b, dtype=torch.long) for b, p in enumerate(pts)]),
        "point_frame": torch.cat([torch.from_numpy(s["point_frame"].astype(np.int64)) for s in samples]),
    }
    targets = {
        "point_label": torch.cat([torch.from_numpy(s["point_label"].astype(np.int64)) for s in samples]),
        "voxel_label": torch.stack([torch.from_numpy(s["voxel_label"].astype(np.int64)) for s in samples]),
        "invalid": torch.stack([torch.from_numpy(s["invalid"].astype(bool)) for s in samples]),
    }
    if all("occluded" in s for s in samples):  # SemanticKITTI's .occluded, where the data reads it
        targets["occluded"] = torch.stack([torch.from_numpy(s["occluded"].astype(bool)) for s in samples])
    if all("scribble" in s for s in samples):  # ScribbleSC labels: 0 empty, 1-19, 254 unlabelled, 255 invalid
        targets["scribble"] = torch.stack([torch.from_numpy(s["scribble"].astype(np.int64)) for s in samples])
    if all("proposal" in s for s in samples):  # VoxFormer's query proposals read from a folder: 1 = proposed
        inputs["proposal"] = torch.stack([torch.from_numpy(s["proposal"].astype(np.uint8)) for s in samples])
    targets["voxel_target"] = targets["voxel_label"].masked_fill(targets["invalid"], IGNORE_INDEX)
    return Batch(inputs, targets, {"size": len(samples)})


def select_frames(batch: Batch, frames: int) -> Batch:
    """Keep the points of the first ``frames`` scans (frame offset < frames), with their point labels."""
    keep = batch.inputs["point_frame"] < frames
    inputs = {**batch.inputs, **{k: batch.inputs[k][keep] for k in ("points", "point_batch", "point_frame")}}
    targets = dict(batch.targets)
    if "point_label" in targets:
        targets["point_label"] = targets["point_label"][keep]
    return Batch(inputs, targets, batch.meta)


def frames_problems(params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
    """A LiDAR adapter's ``frames`` parameter against the scans per sample the data provides."""
    frames: Any = getattr(params, "frames", 1)
    if frames > info.input_frames:
        return [("frames", f"{frames} input frames requested, but the data provides {info.input_frames} "
                           f"(data.params.input_frames)")]
    return []
