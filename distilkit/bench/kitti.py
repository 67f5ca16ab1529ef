"""``distilkit bench kitti``: the real-data path (reading, fusing, evaluating and writing SemanticKITTI-sized frames)
on a folder that ``distilkit data export-kitti`` writes."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.bench.base import Case, register, scratch_dir


@register("kitti")
def kitti_cases(device: torch.device, quick: bool) -> list[Case]:
    """The real-data path at SemanticKITTI's sizes, on a folder `distilkit data export-kitti` writes (one drive of
    HDL-64E-sized scans, ~120k points; --quick: 32 beams): reading and voxelising one scan with its labels
    ('fast') against reading a training sample that fuses 5 scans through the poses with its full-resolution voxel
    labels ('naive' column: the whole sample); and `distilkit eval` of one frame ('fast') against one frame
    predicted and written by `distilkit predict`'s writer ('naive'); a one-scan sample against the same with the
    camera's current and third-previous image decoded, resized and the scan projected as depth. Times per frame: a split of 4,071 frames (sequence
    08) takes 4,071 x the eval time, streaming one frame at a time."""
    from distilkit.data import semantickitti as skio
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.export import export_kitti
    from distilkit.data.params import SemanticKittiParams, SyntheticParams
    from distilkit.data.info import ClassTable
    from distilkit.engine.infer.predict import raw_ids
    from distilkit.metrics.official import evaluate_folder
    from distilkit.structures import VoxelGrid

    import numpy as np

    root = scratch_dir("kitti-")
    beams, steps = (32, 1024) if quick else (64, 2048)
    export_kitti(root, SyntheticParams(beams=beams, azimuth_steps=steps, gt_frames=4), ["08"], frames=6, stride=5)
    seq = root / "sequences" / "08"
    grid = VoxelGrid.semantickitti(1)
    n_points = len(skio.read_points(seq / "velodyne" / "000000.bin"))

    def read_voxelise() -> Tensor:
        pts = skio.read_points(seq / "velodyne" / "000000.bin")
        sem, inst = skio.read_point_labels(seq / "labels" / "000000.label", len(pts))
        idx, inside = grid.index(torch.from_numpy(pts[:, :3]))
        occupied = torch.zeros(grid.shape, dtype=torch.bool)
        occupied[tuple(idx[inside].T)] = True
        return occupied.sum().float() + float(sem.sum() % 7)

    dataset = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], input_frames=5), "val")

    def fused() -> Tensor:
        s = dataset[0]
        return torch.tensor(float(len(s["points"]) + int(s["voxel_label"].sum())))

    preds = root / "preds"
    (preds / "sequences" / "08" / "predictions").mkdir(parents=True)
    raw = skio.read_voxel_labels(seq / "voxels" / "000000.label")
    raw.astype("<u2").reshape(-1).tofile(preds / "sequences" / "08" / "predictions" / "000000.label")
    for f in (seq / "voxels").glob("00000[1-9]*"):
        f.unlink()

    def evaluate() -> Tensor:
        return torch.tensor(evaluate_folder(root, preds, ["08"]).scores["miou"])

    labels = np.zeros(grid.shape, np.int64)

    def write() -> Tensor:
        raw_ids(ClassTable.semantickitti())[labels].astype("<u2").reshape(-1).tofile(preds / "write-test.label")
        return torch.tensor(0.0)

    from distilkit.data.kitti_camera import write_image

    (seq / "image_2").mkdir(exist_ok=True)
    noise = np.random.default_rng(0).integers(0, 256, (376, 1241, 3), dtype=np.uint8)  # incompressible: a worst case
    for j in range(6):
        write_image(seq / "image_2" / f"{j:06d}.png", noise)
    single = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"]), "val")
    camera = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], camera={"previous": [3]}), "val")

    def lidar_sample() -> Tensor:
        return torch.tensor(float(len(single[0]["points"])))

    def camera_sample() -> Tensor:
        s = camera[0]
        return torch.tensor(float(s["image"].shape[0] + (s["depth"] > 0).sum()))

    return [Case("kitti: read+voxelise vs fused sample", f"{n_points:,}-pt scan; 5 scans, 256x256x32",
                 read_voxelise, fused, [], same_value=False),
            Case("kitti: LiDAR sample vs + camera", "1 scan vs + 2 images 1241x376 -> 1220x370, sparse depth",
                 lidar_sample, camera_sample, [], same_value=False),
            Case("kitti: eval vs predict-write, 1 frame", "256x256x32 uint16", evaluate, write, [], same_value=False)]

