"""The SSC metric's range split (VoxFormer's 12.8 / 25.6 m boxes) against VoxFormer's own slicing of the ground
truth, reports of summaries written before the split existed, and a camera model's preview."""

from __future__ import annotations

import numpy as np
import torch

from distilkit.data.batch import Batch
from distilkit.data.info import ClassTable, DataInfo
from distilkit.metrics.registered import SSCScore, range_box
from distilkit.metrics.ssc import ssc_confusion, ssc_scores
from distilkit.structures import VoxelGrid


def voxformer_slice(target: torch.Tensor, r: float) -> torch.Tensor:
    """VoxFormer's ``get_gt_info`` at full resolution (data_metrics.md §2.4), scaled to a grid of 256 / s voxels:
    everything outside the forward box becomes 255."""
    s = 256 // target.shape[1]
    t = target.clone()
    if r == 25.6:
        t[:, 128 // s:, :, :] = 255
        t[:, :, :64 // s, :] = 255
        t[:, :, 192 // s:, :] = 255
    if r == 12.8:
        t[:, 64 // s:, :, :] = 255
        t[:, :, :96 // s, :] = 255
        t[:, :, 160 // s:, :] = 255
    return t


def test_range_scores_equal_voxformers_sliced_ground_truth() -> None:
    grid = VoxelGrid.semantickitti(4)
    info = DataInfo(grid, ClassTable.semantickitti(), frozenset(), ())
    torch.manual_seed(0)
    target = torch.randint(0, 20, (2, *grid.shape)) * (torch.rand(2, *grid.shape) < 0.3)
    invalid = torch.rand(2, *grid.shape) < 0.1
    logits = torch.randn(2, 20, *grid.shape)
    logits[:, 0] += 1.5
    metric = SSCScore(info)
    metric.update(logits, Batch({}, {"voxel_label": target, "invalid": invalid}, {"size": 2}))
    scores = metric.compute()
    pred = logits.argmax(1)
    for r, key in ((12.8, "12_8m"), (25.6, "25_6m"), (51.2, None)):
        want = ssc_scores(ssc_confusion(pred, voxformer_slice(target, r), 20, invalid))
        assert np.isclose(scores[f"miou_{key}" if key else "miou"], want["miou"])
        assert np.isclose(scores[f"iou_{key}" if key else "iou"], want["iou"])
    assert scores["iou_12_8m"] != scores["iou"]  # the boxes select other voxels
    assert int(range_box(grid, 12.8).sum()) == 16 * 16 * 8


def test_a_summary_without_range_scores_is_reported_with_dashes(tmp_path) -> None:
    from distilkit.report.scores import ScoreView, stage_row

    old = {"stage": "s", "adapter": "scpnet", "metric": {"name": "ssc", "key": "miou"}, "steps": 2,
           "test": {"best": {"miou": 0.2, "iou": 0.5, "precision": 0.6, "recall": 0.7}, "best_step": 2,
                    "last": {"miou": 0.2, "iou": 0.5, "precision": 0.6, "recall": 0.7}}}
    row = stage_row(old)
    view: ScoreView = row["view"]
    shown = {c[1]: view.fmt(c, row["best"][c[0]]) for c in view.columns}
    assert shown["mIoU"] == "20.00" and shown["mIoU 12.8 m"] == "—" and shown["IoU 25.6 m"] == "—"


def test_a_camera_models_preview_shows_its_image() -> None:
    grid = VoxelGrid.semantickitti(8)
    info = DataInfo(grid, ClassTable.semantickitti(), frozenset(), ())
    image = torch.rand(1, 2, 3, 6, 10)
    batch = Batch({"image": image}, {"voxel_label": torch.zeros(1, *grid.shape, dtype=torch.long),
                                     "invalid": torch.zeros(1, *grid.shape, dtype=torch.bool)}, {"size": 1})
    view = SSCScore.preview(torch.randn(1, 20, *grid.shape), batch, info)
    assert view["input"].shape == (6, 10, 3) and view["input"].dtype == np.uint8
    assert np.allclose(view["input"] / 255.0, image[0, 0].permute(1, 2, 0).numpy(), atol=1 / 255)
