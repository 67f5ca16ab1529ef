"""``distilkit eval --classes sscbench-kitti360``: SSCBench-KITTI-360's completion scores of a predictions folder.

The scores are SemanticKITTI's (:func:`~distilkit.metrics.ssc.ssc_scores`: one confusion matrix over the split,
completion IoU / precision / recall of occupied against empty, per-class IoU over classes 1..18 with an absent class
counting 0, mIoU their mean), as SSCBench's MonoScene scores them (``method/MonoScene/monoscene/loss/sscMetrics.py``
of ai4ce/SSCBench at 9e767e1: voxels whose target is 255 left out, IoU = tp / (tp + fp + fn), mean over classes
1..18). What differs from SemanticKITTI is the target (:func:`distilkit.data.sscbench.target`): ``.invalid`` drops a
voxel only where its label is 0. VoxFormer's 25.6 m and 12.8 m boxes are scored beside the whole grid (same frame).

A frame's prediction, under ``<predictions>/<drive>/``: ``FFFFFF_1_1.npy`` (train ids 0..18, 256 x 256 x 32, the
format of the benchmark's ``preprocess/labels`` and what ``distilkit predict`` writes; integers, or floats holding
whole numbers — a bool array is refused) or ``FFFFFF.label`` (uint16 raw ids, flat, as its ``voxels/*.label``; mapped
through the learning map). A frame with both is refused: which one is the prediction is not guessed.

Only what scoring needs is read: the targets (``voxels/*.label`` + ``.invalid``, or with ``targets="preprocess"``
``preprocess/labels/*_1_1.npy``) and the predictions, never the input scans; the frames are the drive's
``voxels/*.bin`` as the benchmark lists them (:func:`~distilkit.data.sscbench_folder.drive_frames`), or every
frame with a target where the folder holds no ``.bin``. Everything that can be checked without reading a voxel — the
folders, each frame's files, their formats and sizes — is checked before the first frame is scored
(:func:`plan_sscbench`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, ssc_lut
from distilkit.data.sscbench import LEARNING_MAP, NAMES, SHAPE, SscbenchParams, dtype_problem, read_train_ids
from distilkit.data.sscbench_folder import SscbenchDataset
from distilkit.errors import DataError
from distilkit.metrics.official import RANGES, Evaluation, many, range_mask
from distilkit.metrics.ssc import ssc_scores

VOXELS = int(np.prod(SHAPE))


@dataclass
class SscbenchPlan:
    """What :func:`score_sscbench` scores: the drives' frames (their targets) and each frame's prediction file."""

    data: SscbenchDataset
    files: list[Path]


def prediction_problem(path: Path) -> str | None:
    """What is wrong with a prediction file that its header or size shows (nothing of its voxels read), or None."""
    if path.suffix == ".label":
        size = path.stat().st_size
        return None if size == 2 * VOXELS else (f"{path}: {size:,} bytes, expected {2 * VOXELS:,} (256 x 256 x 32 "
                                                "uint16 raw ids)")
    try:
        head = np.load(path, mmap_mode="r", allow_pickle=False)
    except (ValueError, OSError) as exc:
        return f"{path}: not a readable .npy array ({exc})"
    if head.shape != SHAPE:
        return f"{path}: shape {head.shape}, expected {SHAPE}"
    problem = dtype_problem(head.dtype, len(NAMES))
    return f"{path}: {problem}" if problem else None


def prediction_file(folder: Path, drive: str, frame: str) -> tuple[Path | None, str | None]:
    """(a frame's prediction file, None) or (None, the line saying why there is no one file to read)."""
    npy, label = folder / drive / f"{frame}_1_1.npy", folder / drive / f"{frame}.label"
    if npy.is_file() and label.is_file():
        return None, (f"{folder / drive}/{frame}: both {npy.name} and {label.name} are there (train ids and raw ids); "
                      "keep the one that is the prediction: eval does not guess")
    if npy.is_file() or label.is_file():
        path = npy if npy.is_file() else label
        return path, prediction_problem(path)
    return None, (f"{npy}: no prediction for this frame (expected {npy.name}, train ids, or {label.name}, uint16 raw "
                  "ids)")


def plan_sscbench(dataset_root: str | Path, predictions: str | Path, drives: Sequence[str],
                  targets: str = "voxels") -> SscbenchPlan:
    """Every check made before a voxel is read: the drives' targets (file names and sizes), the predictions folder,
    each drive's folder in it and each frame's one prediction file, its format and size."""
    twice = sorted({d for d in drives if list(drives).count(d) > 1})
    if twice:
        raise DataError(f"{', '.join(twice)}: given twice (a drive is scored once)")
    preds = Path(predictions).expanduser()
    params = SscbenchParams(root=str(dataset_root), train=list(drives), val=None, test=None, targets=targets)
    data = SscbenchDataset(params, "train", what="the evaluated drives", reads="targets")
    if not preds.is_dir():
        raise DataError(f"{preds}: no such folder (the predictions: <drive>/FFFFFF_1_1.npy, train ids, or "
                        "FFFFFF.label, raw ids, one a frame; `distilkit predict` writes them)")
    frames: dict[str, int] = {}
    for drive, _ in data.items:
        frames[drive] = frames.get(drive, 0) + 1
    problems = [f"{preds / drive}: no such folder (the predictions of {drive}'s {n} frames)"
                for drive, n in frames.items() if not (preds / drive).is_dir()]
    files = []
    for drive, frame in data.items:
        if (preds / drive).is_dir():
            path, problem = prediction_file(preds, drive, frame)
            problems += [problem] if problem else []
            files.append(path)
    if problems:
        raise DataError(many(f"{preds}: {len(problems)} predictions cannot be scored", problems))
    return SscbenchPlan(data, files)


def read_prediction_file(path: Path) -> np.ndarray:
    """(X, Y, Z) train ids of one frame's prediction file (see the module docstring for the two formats); a raw id
    the learning map ignores or lacks is 255."""
    if path.suffix == ".npy":
        return read_train_ids(path, len(NAMES))
    raw = skio.read_voxel_labels(path, SHAPE).astype(np.int64)
    lut = ssc_lut(LEARNING_MAP)
    if raw.max() >= len(lut):
        raise DataError(f"{path}: raw id {int(raw.max())} is not an SSCBench-KITTI-360 label id (they lie in "
                        f"[0, {len(lut)}))")
    return lut[raw]


def read_prediction(folder: Path, drive: str, frame: str) -> np.ndarray:
    """(X, Y, Z) train ids of one frame's prediction under ``folder`` (one of the two formats, not both)."""
    path, problem = prediction_file(Path(folder), drive, frame)
    if problem or path is None:
        raise DataError(problem or f"{folder}/{drive}/{frame}: no prediction")
    return read_prediction_file(path)


def score_sscbench(plan: SscbenchPlan, progress: Callable[[int, int], None] | None = None) -> Evaluation:
    """The scores of a :func:`plan_sscbench` (see the module docstring)."""
    data, k = plan.data, len(NAMES)
    region = (range_mask(RANGES[1]).astype(np.int64) + range_mask(RANGES[0])).reshape(-1)  # 0 out, 1: 25.6, 2: 12.8
    conf = np.zeros((3, k, k), np.int64)
    for n, path in enumerate(plan.files):
        labels, invalid = data.dense_target(n)
        gt = labels.reshape(-1).astype(np.int64)
        keep = (gt != IGNORE_INDEX) & ~invalid.reshape(-1)
        pred = read_prediction_file(path).reshape(-1).astype(np.int64)[keep]
        bad = int((pred == IGNORE_INDEX).sum())
        if bad:
            what = ("predicted 255" if path.suffix == ".npy" else
                    "given raw ids kitti360.yaml's learning map ignores or lacks")
            raise DataError(f"{path}: {bad:,} scored voxels are {what}: a prediction names a class 0..18 wherever a "
                            "voxel is scored")
        conf += np.bincount((region[keep] * k + pred) * k + gt[keep], minlength=3 * k * k).reshape(3, k, k)
        if progress:
            progress(n + 1, len(plan.files))
    boxes = {RANGES[1]: conf[1:].sum(axis=0), RANGES[0]: conf[2]}
    return Evaluation(len(plan.files), ssc_scores(conf.sum(axis=0)), {r: ssc_scores(c) for r, c in boxes.items()},
                      NAMES)


def evaluate_sscbench(dataset_root: str | Path, predictions: str | Path, drives: Sequence[str],
                      progress: Callable[[int, int], None] | None = None, targets: str = "voxels") -> Evaluation:
    """The scores of ``predictions`` over every frame of ``drives`` (:func:`plan_sscbench`, then
    :func:`score_sscbench`)."""
    return score_sscbench(plan_sscbench(dataset_root, predictions, drives, targets), progress)


__all__ = ["SscbenchPlan", "evaluate_sscbench", "plan_sscbench", "prediction_file", "read_prediction",
           "read_prediction_file", "score_sscbench"]
