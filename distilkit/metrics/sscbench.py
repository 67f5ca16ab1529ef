"""``distilkit eval --classes sscbench-kitti360``: SSCBench-KITTI-360's completion scores of a predictions folder.

The scores are SemanticKITTI's (:func:`~distilkit.metrics.ssc.ssc_scores`: one confusion matrix over the split,
completion IoU / precision / recall of occupied against empty, per-class IoU over classes 1..18 with an absent class
counting 0, mIoU their mean), as SSCBench's MonoScene scores them (``method/MonoScene/monoscene/loss/sscMetrics.py``
of ai4ce/SSCBench at 9e767e1: voxels whose target is 255 left out, IoU = tp / (tp + fp + fn), mean over classes
1..18). What differs from SemanticKITTI is the target (:func:`distilkit.data.sscbench.target`): ``.invalid`` drops a
voxel only where its label is 0. VoxFormer's 25.6 m and 12.8 m boxes are scored beside the whole grid (same frame).

A frame's prediction, under ``<predictions>/<drive>/``: ``FFFFFF_1_1.npy`` (train ids 0..18, 256 x 256 x 32, the
format of the benchmark's ``preprocess/labels``) or ``FFFFFF.label`` (uint16 raw ids, flat, as its ``voxels/*.label``;
mapped through the learning map).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, ssc_lut
from distilkit.data.sscbench import LEARNING_MAP, NAMES, SHAPE, SscbenchDataset, SscbenchParams, read_train_ids
from distilkit.errors import DataError
from distilkit.metrics.official import RANGES, Evaluation, range_mask
from distilkit.metrics.ssc import ssc_scores


def read_prediction(folder: Path, drive: str, frame: str) -> np.ndarray:
    """(X, Y, Z) train ids of one frame's prediction (see the module docstring for the two formats)."""
    npy, label = folder / drive / f"{frame}_1_1.npy", folder / drive / f"{frame}.label"
    if npy.is_file():
        pred = read_train_ids(npy, len(NAMES))
    elif label.is_file():
        raw = skio.read_voxel_labels(label, SHAPE).astype(np.int64)
        lut = ssc_lut(LEARNING_MAP)
        if raw.max() >= len(lut):
            raise DataError(f"{label}: raw id {int(raw.max())} is not an SSCBench-KITTI-360 label")
        pred = lut[raw]
    else:
        raise DataError(f"{npy}: no prediction for this frame (expected {npy.name}, train ids, or {label.name}, "
                        "uint16 raw ids)")
    return pred


def evaluate_sscbench(dataset_root: str | Path, predictions: str | Path, drives: Sequence[str],
                      progress: Callable[[int, int], None] | None = None, targets: str = "voxels") -> Evaluation:
    """The scores of ``predictions`` over every labelled frame of ``drives`` (see the module docstring)."""
    params = SscbenchParams(root=str(dataset_root), train=list(drives), val=None, test=None, targets=targets)
    data = SscbenchDataset(params, "train", what="the evaluated drives")
    preds = Path(predictions).expanduser()
    k = len(NAMES)
    region = (range_mask(RANGES[1]).astype(np.int64) + range_mask(RANGES[0])).reshape(-1)  # 0 out, 1: 25.6, 2: 12.8
    conf = np.zeros((3, k, k), np.int64)
    for n, (drive, frame) in enumerate(data.items):
        labels, invalid = data.dense_target(n)
        gt = labels.reshape(-1).astype(np.int64)
        keep = (gt != IGNORE_INDEX) & ~invalid.reshape(-1)
        pred = read_prediction(preds, drive, frame).reshape(-1).astype(np.int64)[keep]
        if (pred == IGNORE_INDEX).any():
            raise DataError(f"{preds / drive}/{frame}: {int((pred == IGNORE_INDEX).sum())} scored voxels are predicted "
                            "255 (or a raw id the learning map ignores): a prediction names a class 0..18 everywhere")
        conf += np.bincount((region[keep] * k + pred) * k + gt[keep], minlength=3 * k * k).reshape(3, k, k)
        if progress:
            progress(n + 1, len(data.items))
    boxes = {RANGES[1]: conf[1:].sum(axis=0), RANGES[0]: conf[2]}
    return Evaluation(len(data.items), ssc_scores(conf.sum(axis=0)), {r: ssc_scores(c) for r, c in boxes.items()},
                      NAMES)


__all__ = ["evaluate_sscbench", "read_prediction"]
