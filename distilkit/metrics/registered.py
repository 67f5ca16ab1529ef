"""The registered metrics' accumulators; their declarations and registrations are their cards'
(:mod:`distilkit.cards.metrics`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from distilkit.cards.metrics import EMDScoreCard, OccupancyScoreCard, SSCScoreCard, SceneCompletionScoreCard, \
    range_key
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.metrics.base import Metric
from distilkit.metrics.bev import thin, top_class
from distilkit.metrics.points import auc, chamfer_distance, emd, jsd_3d, jsd_bev, precision_recall_curves, \
    voxel_confusion
from distilkit.metrics.ssc import SSCMetric, ssc_confusion


def camera_image(batch: Batch) -> np.ndarray | None:
    """The batch's first RGB image as (H, W, 3) uint8 (``image`` (B, T, 3, H, W) or (B, 3, H, W), 0..1), or None."""
    image = batch.inputs.get("image")
    if image is None or image.dim() not in (4, 5):
        return None
    first = image[0, 0] if image.dim() == 5 else image[0]
    if first.shape[0] != 3:
        return None
    return (first.permute(1, 2, 0).clamp(0, 1) * 255).round().byte().cpu().numpy()


def range_box(grid: Any, r: float) -> Tensor:
    """(X, Y, Z) bool: the voxels whose centres lie in VoxFormer's evaluation box of range ``r`` in front of the
    sensor, x in [0, r) and y in [-r/2, r/2) metres (z uncropped; data_metrics.md §2.4)."""
    import torch

    x = grid.origin[0] + (torch.arange(grid.shape[0]) + 0.5) * grid.voxel_size
    y = grid.origin[1] + (torch.arange(grid.shape[1]) + 0.5) * grid.voxel_size
    inside = ((x >= 0) & (x < r))[:, None] & ((y >= -r / 2) & (y < r / 2))[None, :]
    return inside[:, :, None].expand(*grid.shape)


class SSCScore(SSCScoreCard, Metric):
    """Voxel logits scored as SemanticKITTI SSC: the argmax class per voxel against ``voxel_label``, voxels
    flagged ``invalid`` left out, one confusion matrix over the split (the sum of the scenes' own, whose
    intersections and unions :meth:`per_scene` keeps: a bootstrap over the test scenes reads them)."""

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.acc = SSCMetric(info.num_classes, info.classes.ignore_index)
        self.ranges = {range_key(r): SSCMetric(info.num_classes, info.classes.ignore_index) for r in self.RANGES}
        self.scene_ids: list[str] = []
        self.scene_counts: list[Tensor] = []  # per scene: (2, K - 1) intersections and unions of classes 1..K-1

    def update(self, prediction: Tensor, batch: Batch) -> None:
        pred = prediction.argmax(dim=1).cpu()
        target, invalid = batch.targets["voxel_label"].cpu(), batch.targets["invalid"].cpu()
        for i in range(len(pred)):  # scene by scene: integer counts, so their sum is the batch's confusion exactly
            conf = ssc_confusion(pred[i], target[i], self.acc.num_classes, invalid[i], self.acc.ignore_index)
            self.acc.confusion += conf
            tp = conf.diagonal()
            self.scene_counts.append(torch.stack([tp, conf.sum(0) + conf.sum(1) - tp])[:, 1:].clone())
        self.scene_ids += [str(s) for s in batch.meta.get("sample_id") or [""] * len(pred)]
        grid = self.info.grid
        if grid is None or tuple(grid.shape) != tuple(target.shape[1:]):
            return
        for r in self.RANGES:
            outside = ~range_box(grid, r)
            self.ranges[range_key(r)].update(pred, target, invalid | outside)

    def compute(self) -> dict[str, Any]:
        out = self.acc.compute()
        for key, acc in self.ranges.items():
            scores = acc.compute()
            out.update({f"miou_{key}": scores["miou"], f"iou_{key}": scores["iou"]})
        return out

    def per_scene(self) -> dict[str, Any] | None:
        """Each scored scene's id and its intersections and unions of classes 1..K-1 ((J, K - 1) int64 each)."""
        if not self.scene_counts:
            return None
        counts = torch.stack(self.scene_counts).numpy()
        return {"ids": list(self.scene_ids), "inter": counts[:, 0], "union": counts[:, 1]}

    @classmethod
    def preview(cls, prediction: Tensor, batch: Batch, info: DataInfo) -> dict[str, Any] | None:
        """The first scene from above: its current input scan (a camera model: its current image), the predicted and
        the true class per column."""
        if info.grid is None:
            return None
        g = info.grid
        out: dict[str, Any] = {
            "prediction": top_class(prediction[0].argmax(dim=0), info.classes.ignore_index),
            "target": top_class(batch.targets["voxel_label"][0], info.classes.ignore_index),
            "extent": np.array([g.origin[0], g.origin[0] + g.shape[0] * g.voxel_size,
                                g.origin[1], g.origin[1] + g.shape[1] * g.voxel_size], dtype=np.float32)}
        image = camera_image(batch)
        if image is not None:  # a camera model: its (current) image beside the views from above
            out["input"] = image
        elif "points" in batch.inputs and "point_batch" in batch.inputs:
            first = batch.inputs["point_batch"] == 0
            if "point_frame" in batch.inputs:
                first &= batch.inputs["point_frame"] == 0
            out["input"] = thin(batch.inputs["points"][first])
        return out


class OccupancyScore(OccupancyScoreCard, Metric):
    """Empty / occupied scores (query proposals) against the occupancy of ``voxel_label`` pooled to their grid
    (invalid voxels left out): IoU, precision and recall of the occupied class over the split (VoxFormer's stage-1
    numbers)."""

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.acc = SSCMetric(2, info.classes.ignore_index)

    def update(self, prediction: Tensor, batch: Batch) -> None:
        from distilkit.geometry.voxel import pool_occupancy

        ignore = self.info.classes.ignore_index
        target = batch.targets["voxel_label"].masked_fill(batch.targets["invalid"].bool(), ignore).cpu()
        occupancy = pool_occupancy(target.long(), target.shape[1] // prediction.shape[2], ignore)
        self.acc.update(prediction.argmax(dim=1).cpu(), occupancy)

    def compute(self) -> dict[str, Any]:
        scores = self.acc.compute()
        return {k: scores[k] for k in self.KEYS}


class SceneCompletionScore(SceneCompletionScoreCard, Metric):
    """Point-cloud completions scored as LiDiff's ``eval_path.py`` scores them (data_metrics.md §3): against the
    untiled evaluation ground truth ``scene_eval`` (the map crop, -4 < z < 4.4), predicted points with a 3-D range
    of 50 m or more dropped first; Chamfer distance (m) and BEV Jensen-Shannon distance averaged over scenes (also
    ``jsd_3d``, the 3-D point-count variant Distillation-DPO ranks by); occupied-voxel IoU at 0.5 / 0.2 / 0.1 m over
    the whole split (also ``iou_*_rounded``: LiDiff's IoU before its June 2025 fix, the one ScoreLiDAR's tables use);
    precision, recall and F (per scene and threshold F = 2PR / (P + R)) averaged over scenes per threshold, then the
    normalised area over 5-10 cm. (The z-crop post-processing of LiDiff's pipeline is the model's: LiDiff's
    completion applies it before any refinement.)"""

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.cd: list[float] = []
        self.jsd: list[float] = []
        self.jsd_3d: list[float] = []
        # (TP, FP, FN) per voxel size as tensors: a multi-process merge adds them (a list would be concatenated)
        self.confusion = {k: torch.zeros(3, dtype=torch.int64) for k in self.VOXELS}
        self.rounded = {k: torch.zeros(3, dtype=torch.int64) for k in self.VOXELS}
        self.precision: list[Tensor] = []
        self.recall: list[Tensor] = []
        self.fscore: list[Tensor] = []

    def update(self, prediction: Any, batch: Batch) -> None:
        target = batch.targets["scene_eval"].cpu()
        lengths = batch.targets["scene_eval_lengths"].cpu()
        for b in range(batch.size):
            pred = prediction.cloud(b).detach().cpu().double()
            pred = pred[pred.norm(dim=1) < self.MAX_RANGE]
            gt = target[b, : int(lengths[b])].double()
            if len(pred) == 0:
                raise ValueError(f"scene {b} of the batch: no predicted point within {self.MAX_RANGE:g} m")
            self.cd.append(chamfer_distance(pred, gt))
            self.jsd.append(jsd_bev(pred, gt))
            self.jsd_3d.append(jsd_3d(pred, gt))
            for key, size in self.VOXELS.items():
                self.confusion[key] += torch.tensor(voxel_confusion(pred, gt, size))
                self.rounded[key] += torch.tensor(voxel_confusion(pred, gt, size, rounded=True))
            p, r = precision_recall_curves(pred, gt)
            self.precision.append(p)
            self.recall.append(r)
            self.fscore.append(torch.where(p + r > 0, 2 * p * r / (p + r).clamp_min(1e-300), torch.zeros_like(p)))

    def compute(self) -> dict[str, Any]:
        n = max(len(self.cd), 1)
        out: dict[str, Any] = {"cd": sum(self.cd) / n, "jsd": sum(self.jsd) / n, "jsd_3d": sum(self.jsd_3d) / n}
        for suffix, confusion in (("", self.confusion), ("_rounded", self.rounded)):
            for key, (tp, fp, fn) in confusion.items():
                out[f"{key}{suffix}"] = int(tp) / (int(tp) + int(fp) + int(fn) + 1e-15)
        if self.precision:
            p, r, f = (torch.stack(v).mean(0) for v in (self.precision, self.recall, self.fscore))
            out.update(precision=auc(p), recall=auc(r), fscore=auc(f))
        else:
            out.update(precision=0.0, recall=0.0, fscore=0.0)
        return out

    @classmethod
    def preview(cls, prediction: Any, batch: Batch, info: DataInfo) -> dict[str, Any] | None:
        """The first scene from above: the scan, the completed and the true scene (points within 50 m)."""
        target = thin(batch.targets["scene_eval"][0, : int(batch.targets["scene_eval_lengths"][0])])
        low, high = target[:, :2].min(axis=0) - 2.0, target[:, :2].max(axis=0) + 2.0  # the scene, 2 m around
        out = {"prediction": thin(prediction.cloud(0)), "target": target,
               "extent": np.array([low[0], high[0], low[1], high[1]], dtype=np.float32)}
        if "scan" in batch.inputs:
            lengths = batch.inputs.get("scan_lengths")
            n = int(lengths[0]) if lengths is not None else batch.inputs["scan"].shape[1]
            out["input"] = thin(batch.inputs["scan"][0, :n])
        return out


class EMDScore(EMDScoreCard, Metric):
    """The earth mover's distance of each completion to its evaluation ground truth (``scene_eval``; predicted points
    of 3-D range 50 m or more dropped, as :class:`SceneCompletionScore`), averaged over scenes: exact on 2,048-point
    seeded subsamples (:func:`distilkit.metrics.points.emd`). About 0.7 s a scene on a 2-core CPU, so it is a metric of
    its own (``train.metrics: [emd]``)."""

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.values: list[float] = []

    def update(self, prediction: Any, batch: Batch) -> None:
        target, lengths = batch.targets["scene_eval"].cpu(), batch.targets["scene_eval_lengths"].cpu()
        for b in range(batch.size):
            pred = prediction.cloud(b).detach().cpu().double()
            self.values.append(emd(pred[pred.norm(dim=1) < SceneCompletionScore.MAX_RANGE],
                                   target[b, : int(lengths[b])].double()))

    def compute(self) -> dict[str, Any]:
        return {"emd": sum(self.values) / max(len(self.values), 1)}


__all__ = ["EMDScore", "OccupancyScore", "SSCScore", "SceneCompletionScore", "camera_image", "range_box", "range_key"]
