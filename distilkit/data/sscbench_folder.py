"""An SSCBench-KITTI-360 folder as a dataset (``sscbench-kitti360``; the benchmark's layout, formats, classes and the
recipe's parameters are :mod:`distilkit.data.sscbench`'s): the frames read as samples. A drive's frames listed, each
frame's files checked by their sizes, the checks ``validate`` makes of a folder (one frame's labels a drive) and its
fingerprint (the names, sizes and modification times of its files) are :mod:`distilkit.data.sscbench_listing`'s
(torch-free; re-exported here). :mod:`distilkit.cards.datasets` declares it.
"""

from __future__ import annotations

import numpy as np
import torch

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, ssc_lut
from distilkit.data.kitti_folder import pool_all, pool_labels
from distilkit.data.sscbench import (LEARNING_MAP, NAMES, SHAPE, SscbenchParams, class_table, read_train_ids,
                                     read_voxel_mask, sscbench_info, target)
from distilkit.data.sscbench_listing import (Reads, SscbenchFrames, drive_frames, first_frame_problems,
                                             frame_problems, sscbench_check, sscbench_fingerprint, sscbench_notes,
                                             unmapped_problem)
from distilkit.structures import VoxelGrid


class SscbenchDataset(SscbenchFrames, torch.utils.data.Dataset):
    """An SSCBench-KITTI-360 folder's frames of one role: every ``voxels/*.bin`` of its drives (module docstring).
    ``reads``: what is read and checked — ``all`` (training), ``targets`` (scoring: no input scan is read) or
    ``inputs`` (predicting: no target is read; the samples' targets are ignored everywhere)."""

    def __init__(self, params: SscbenchParams, split: str, what: str | None = None, reads: Reads = "all") -> None:
        super().__init__(params, split, what, reads)
        self.table = class_table()
        self.lut = ssc_lut(LEARNING_MAP)
        self.info = sscbench_info(params)
        self.has_targets = reads != "inputs"
        self._grid = VoxelGrid.semantickitti(1)

    def dense_target(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(train ids 0..18 with 255, the ignored mask the train ids do not already carry) at full resolution."""
        drive, frame = self.items[i]
        if self.p.targets == "preprocess":
            ids = read_train_ids(self.root / "preprocess" / "labels" / drive / f"{frame}_1_1.npy", len(NAMES))
            return ids, np.zeros(SHAPE, bool)
        vox = self.root / "data_2d_raw" / drive / "voxels"
        raw = skio.read_voxel_labels(vox / f"{frame}.label", SHAPE)
        return target(raw, read_voxel_mask(vox / f"{frame}.invalid", "invalid mask"), self.lut,
                      str(vox / f"{frame}.label"))

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        drive, frame = self.items[i]
        labels, invalid = self.dense_target(i) if self.has_targets else (np.full(SHAPE, IGNORE_INDEX, np.uint8),
                                                                         np.ones(SHAPE, bool))
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


__all__ = ["Reads", "SscbenchDataset", "SscbenchFrames", "drive_frames", "first_frame_problems", "frame_problems",
           "sscbench_check", "sscbench_fingerprint", "sscbench_notes", "unmapped_problem"]
