"""SemanticKITTI-format folders as a dataset: scans fused through the poses with their voxel targets at the grid's
scale (SemanticKITTI's labels pooled as the benchmark does), scribbles, query proposals and the camera where the
folder has them. The folder's listing, the checks ``validate`` makes of its files and its fingerprint (the names,
sizes and modification times of its files) that stands for the data in a stage's identity are
:mod:`distilkit.data.kitti_listing`'s (torch-free; re-exported here). :mod:`distilkit.cards.datasets` declares it
under its names."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, NUM_CLASSES, remap, seg_lut, ssc_lut
from distilkit.data.kitti_listing import (SemanticKittiFolder, folder_problems, kitti_check, kitti_fingerprint,
                                          kitti_info, scan_problems)
from distilkit.data.params import SemanticKittiParams
from distilkit.data.proposals import proposal_file, proposal_root, read_proposal
from distilkit.data.scribbles import pool_scribbles, read_scribbles, scribble_file, scribble_root
from distilkit.errors import DataError
from distilkit.structures import VoxelGrid


def pool_all(mask: np.ndarray, scale: int) -> np.ndarray:
    """Coarsen an (X,Y,Z) bool grid by ``scale``: a coarse voxel is set when all its fine voxels are."""
    if scale == 1:
        return mask
    x, y, z = mask.shape
    return mask.reshape(x // scale, scale, y // scale, scale, z // scale, scale).all(axis=(1, 3, 5))


def pool_labels(labels: np.ndarray, invalid: np.ndarray, scale: int,
                num_classes: int = NUM_CLASSES) -> tuple[np.ndarray, np.ndarray]:
    """Coarsen a (X,Y,Z) label grid by ``scale``: majority of non-empty valid labels, else empty/255."""
    if scale == 1:
        return labels, invalid
    x, y, z = labels.shape
    blocks = labels.reshape(x // scale, scale, y // scale, scale, z // scale, scale).transpose(0, 2, 4, 1, 3, 5)
    blocks = blocks.reshape(x // scale, y // scale, z // scale, -1)
    inv = pool_all(invalid, scale)
    counts = np.stack([(blocks == c).sum(-1) for c in range(1, num_classes)], -1)
    out = np.where(counts.max(-1) > 0, counts.argmax(-1) + 1, 0)
    out = np.where((blocks == IGNORE_INDEX).all(-1), IGNORE_INDEX, out)
    return out.astype(np.uint8), inv


class SemanticKittiDataset(SemanticKittiFolder, torch.utils.data.Dataset):
    """A SemanticKITTI-format folder: scans, point labels, SSC voxel labels and invalid masks (the labelled
    every-5th frames; with ``semantickitti-scan``'s parameters every scan, its voxel targets ignored where the frame
    has none)."""

    def __init__(self, params: SemanticKittiParams, split: str, what: str | None = None) -> None:
        """The role ``split`` (train, val, test) of the folder; ``what`` names it in errors (default: the role)."""
        super().__init__(params, split, what)
        self.info = kitti_info(params)
        self.has_targets = any(item[3] for item in self.items)  # False: the hidden test split, predicted only
        self._ids = "SemanticPOSS" if params.classes == "semanticposs" else "SemanticKITTI"  # whose raw ids, in errors
        self._poses: dict[Path, np.ndarray] = {}
        self._calibs: dict[Path, dict[str, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.items)

    def sample_id(self, i: int) -> str:
        """``<sequence>/<frame>``, as SemanticKITTI names its files (published predictions are stored by it)."""
        d, frame = self.items[i][:2]
        return f"{d.name}/{frame:06d}"

    def _rectified(self, d: Path, frame: int, labels: np.ndarray) -> np.ndarray:
        """SCPNet's rectification of a frame's full-resolution labels with its own scan's panoptic labels."""
        from distilkit.data.rectify import dynamic_ids, rectify_frame

        return rectify_frame(d, frame, labels, dynamic_ids(self.p.rectify_classes, self.table.names),
                             dict(self.table.learning_map))

    def _calib(self, d: Path) -> dict[str, np.ndarray]:
        if d not in self._calibs:
            self._calibs[d] = skio.read_calib(d / "calib.txt")
        return self._calibs[d]

    def _pose(self, d: Path) -> np.ndarray:
        """The sequence's LiDAR poses: one per scan (a poses.txt with fewer is named)."""
        if d not in self._poses:
            poses = skio.read_poses(d / "poses.txt", self._calib(d))
            scans = len(list((d / "velodyne").glob("*.bin")))
            if len(poses) < scans:
                raise DataError(f"{d / 'poses.txt'}: {len(poses)} poses for the {scans} scans of velodyne/ (one pose "
                                "a scan, in order)")
            self._poses[d] = poses
        return self._poses[d]

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        sample = self._lidar(i)
        cam = self.p.camera
        if cam is not None:
            from distilkit.data.camera import frame_offsets
            from distilkit.data.kitti_camera import camera_sample

            d, frame = self.items[i][:2]
            scan = sample["points"][sample["point_frame"] == 0]
            sample.update(camera_sample(d, frame, frame_offsets(cam), cam.height, cam.width, cam.max_depth,
                                        self._pose(d) if cam.previous else None, self._calib(d), scan))
        return sample

    def _lidar(self, i: int) -> dict[str, np.ndarray]:
        """The fused scans, their point labels and the voxel targets of item ``i`` (full-resolution labels pooled
        to the dataset's scale), and its query proposals where the parameters read them."""
        out = self._scans_and_voxels(i)
        if self.p.proposals:
            d, frame = self.items[i][:2]
            path = proposal_file(proposal_root(self.p.root, self.p.proposals), d.name, frame)
            if path is None:
                raise DataError(f"{proposal_root(self.p.root, self.p.proposals) / d.name / 'queries'}/{frame:06d}.*: "
                                f"missing (proposals: {self.p.proposals} reads it)")
            out["proposal"] = read_proposal(path, self.p.scale)
        return out

    def _scans_and_voxels(self, i: int) -> dict[str, np.ndarray]:
        d, frame, n, labelled = self.items[i]
        pts, labs, frames = [], [], []
        for k in range(self.p.input_frames):
            j = frame + k
            if j >= n:
                break
            p = skio.read_points(d / "velodyne" / f"{j:06d}.bin")
            lab_file = d / "labels" / f"{j:06d}.label"
            sem = skio.read_point_labels(lab_file, len(p))[0] if lab_file.is_file() else np.zeros(len(p), np.int64)
            if k > 0:
                poses = self._pose(d)
                rel = np.linalg.inv(poses[frame]) @ poses[j]
                p = p.copy()
                p[:, :3] = p[:, :3] @ rel[:3, :3].T + rel[:3, 3]
            pts.append(p)
            labs.append(remap(sem, seg_lut(self.table.learning_map), str(lab_file), self._ids))
            frames.append(np.full(len(p), k, np.uint8))
        vox_file = d / self.p.voxels / f"{frame:06d}.label"
        if not labelled:  # hidden test split, or a scan between voxel frames: nothing to score
            shape = VoxelGrid.semantickitti(self.p.scale).shape
            return {"points": np.concatenate(pts), "point_frame": np.concatenate(frames),
                    "point_label": np.concatenate(labs).astype(np.uint8),
                    "voxel_label": np.full(shape, IGNORE_INDEX, np.uint8), "invalid": np.ones(shape, bool),
                    **({"occluded": np.zeros(shape, bool)} if self.p.occluded else {}),
                    **({"scribble": np.full(shape, IGNORE_INDEX, np.uint8)} if self.p.scribbles else {})}
        vl = remap(skio.read_voxel_labels(vox_file), ssc_lut(self.table.learning_map), str(vox_file), self._ids)
        inv_file = d / "voxels" / f"{frame:06d}.invalid"
        inv = skio.read_voxel_bits(inv_file) if inv_file.is_file() else np.zeros(vl.shape, bool)
        if self.p.rectify:
            vl = self._rectified(d, frame, vl)
        dense = vl
        vl, pooled = pool_labels(vl, inv, self.p.scale, self.table.num_classes)
        out = {"points": np.concatenate(pts), "point_frame": np.concatenate(frames),
               "point_label": np.concatenate(labs).astype(np.uint8), "voxel_label": vl.astype(np.uint8),
               "invalid": pooled}
        if self.p.occluded:  # occluded from the current viewpoint (not used by the official evaluation)
            occ = skio.read_voxel_bits(d / "voxels" / f"{frame:06d}.occluded")
            out["occluded"] = pool_all(occ, self.p.scale)
        if self.p.scribbles:  # ScribbleSC's scribbles, told from empty voxels by the dense geometry
            path = scribble_file(scribble_root(self.p.root, self.p.scribbles), d.name, frame)
            scribble = read_scribbles(path, dense, inv, dict(self.table.learning_map))
            out["scribble"] = pool_scribbles(scribble, self.p.scale, self.table.num_classes)
        return out


__all__ = ["SemanticKittiDataset", "SemanticKittiFolder", "folder_problems", "kitti_check", "kitti_fingerprint",
           "kitti_info", "pool_all", "pool_labels", "scan_problems"]
