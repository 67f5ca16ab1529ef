"""``distilkit eval``: SemanticKITTI's official completion evaluation (``evaluate_completion.py``, data_metrics.md §1.8)
of a predictions folder against a dataset folder, and VoxFormer's range split (§2.4).

Every ``sequences/NN/voxels/NNNNNN.label`` of the split's sequences is a frame to score; its prediction is
``<predictions>/sequences/NN/predictions/NNNNNN.label`` (uint16 raw ids, 256 x 256 x 32, flat). Both go through the
SSC table (raw -> 0..19, 255 ignored); voxels whose target is 255 or that are ``.invalid`` are left out; one
confusion matrix over the whole split (frames are streamed: memory is one frame); mIoU over classes 1..19 with an
absent class counting 0. A prediction that maps to 255 where it is scored is an error (the official script crashes
there). VoxFormer's 25.6 m and 12.8 m boxes in front of the car are scored beside the whole 51.2 m grid. The folders
and each prediction's presence and size are checked before the first frame is read (:func:`plan_folder`): a missing
predictions folder is named as a folder, a missing file as a frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.classes import CLASS_NAMES, IGNORE_INDEX, ssc_lut
from distilkit.data.info import ClassTable
from distilkit.errors import DataError
from distilkit.metrics.ssc import ssc_scores
from distilkit.structures import VoxelGrid

RANGES = (12.8, 25.6)  # VoxFormer's boxes; 51.2 m is the whole grid
VOXELS = 256 * 256 * 32


def range_mask(r: float) -> np.ndarray:
    """(256, 256, 32) bool: VoxFormer's box of range ``r`` on the full grid, x in [0, r), y in [-r/2, r/2) (the index
    slices of §2.4; :func:`~distilkit.metrics.registered.range_box`, which the in-training metric uses)."""
    from distilkit.metrics.registered import range_box

    return range_box(VoxelGrid.semantickitti(1), r).numpy()


@dataclass
class Evaluation:
    frames: int
    scores: dict[str, Any]  # the whole grid's iou, precision, recall, miou, class_iou
    ranges: dict[float, dict[str, Any]]
    names: tuple[str, ...] = tuple(CLASS_NAMES)  # the class table's names (0 = empty)


def frames_of(dataset_root: Path, sequences: Sequence[str]) -> list[tuple[str, Path]]:
    """(sequence, ground-truth label file) of every frame to score, in order."""
    out = []
    for seq in sequences:
        vox = dataset_root / "sequences" / seq / "voxels"
        if not vox.is_dir():
            raise DataError(f"{dataset_root}: no sequences/{seq}/voxels/ folder (the split's ground truth)")
        out += [(seq, f) for f in sorted(vox.glob("*.label"))]
    if not out:
        raise DataError(f"{dataset_root}: no sequences/NN/voxels/*.label for sequences {', '.join(sequences)}")
    return out


def many(head: str, problems: list[str], shown: int = 12) -> str:
    """One problem as its own line; several under ``head``, the first ``shown`` of them listed."""
    if len(problems) == 1:
        return problems[0]
    more = [f"... and {len(problems) - shown} more"] if len(problems) > shown else []
    return head + ":\n  " + "\n  ".join(problems[:shown] + more)


def plan_folder(dataset_root: str | Path, predictions: str | Path,
                sequences: Sequence[str]) -> list[tuple[str, Path, Path]]:
    """(sequence, ground truth, prediction) of every frame to score, once the folders and each prediction's size
    are checked (nothing of a voxel read): a missing folder is named as a folder, a missing file as a frame."""
    root, preds = Path(dataset_root).expanduser(), Path(predictions).expanduser()
    frames = frames_of(root, sequences)
    if not preds.is_dir():
        raise DataError(f"{preds}: no such folder (the predictions: sequences/NN/predictions/NNNNNN.label; "
                        "`distilkit predict` writes them)")
    problems = [f"{preds / 'sequences' / seq / 'predictions'}: no such folder (the predictions of sequence {seq})"
                for seq in dict.fromkeys(seq for seq, _ in frames)
                if not (preds / "sequences" / seq / "predictions").is_dir()]
    jobs = []
    for seq, gt_file in frames:
        pred_file = preds / "sequences" / seq / "predictions" / gt_file.name
        if not pred_file.parent.is_dir():
            continue
        if not pred_file.is_file():
            problems.append(f"{pred_file}: no prediction for this frame (expected a uint16 .label per ground-truth "
                            "frame)")
        elif pred_file.stat().st_size != 2 * VOXELS:
            problems.append(_size_problem(pred_file))
        jobs.append((seq, gt_file, pred_file))
    if problems:
        raise DataError(many(f"{preds}: {len(problems)} predictions cannot be scored", problems))
    return jobs


def _size_problem(path: Path) -> str:
    size = path.stat().st_size
    return (f"{path}: {size // 2:,} voxels, expected {VOXELS:,} (256 x 256 x 32 uint16)" if size % 2 == 0 else
            f"{path}: {size:,} bytes, expected {2 * VOXELS:,} (256 x 256 x 32 uint16)")


def _read_prediction(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path}: no prediction for this frame (expected a uint16 .label per ground-truth frame)")
    raw = np.fromfile(path, dtype="<u2")
    if raw.size != VOXELS:
        raise DataError(_size_problem(path))
    return raw.astype(np.int64)


def _regions() -> np.ndarray:
    """(256*256*32,) int64 flat: 0 outside VoxFormer's 25.6 m box, 1 inside it but outside the 12.8 m box, 2 inside
    that; one code per voxel lets one bincount give all three confusions."""
    return (range_mask(RANGES[1]).astype(np.int64) + range_mask(RANGES[0])).reshape(-1)


def evaluate_folder(dataset_root: str | Path, predictions: str | Path, sequences: Sequence[str],
                    progress: Callable[[int, int], None] | None = None, table: ClassTable | None = None,
                    jobs: list[tuple[str, Path, Path]] | None = None) -> Evaluation:
    """The official scores of ``predictions`` over the frames of ``sequences`` (see the module docstring);
    ``table``: the labels' class table (default SemanticKITTI's; SemanticPOSS's for its folders); ``jobs``: the
    frames :func:`plan_folder` checked (else it is called here)."""
    table = table or ClassTable.semantickitti()
    lut, k = ssc_lut(dict(table.learning_map)), table.num_classes
    regions = _regions()
    conf = np.zeros((3, k, k), np.int64)  # per region code
    jobs = plan_folder(dataset_root, predictions, sequences) if jobs is None else jobs
    for n, (seq, gt_file, pred_file) in enumerate(jobs):
        raw_pred = _read_prediction(pred_file)
        if raw_pred.max() >= len(lut):
            raise DataError(f"{pred_file}: raw id {int(raw_pred.max())} is not a SemanticKITTI label")
        target = lut[skio.read_voxel_labels(gt_file).reshape(-1).astype(np.int64)]
        inv_file = gt_file.with_suffix(".invalid")
        scored = target != IGNORE_INDEX
        if inv_file.is_file():
            scored &= ~skio.read_voxel_bits(inv_file).reshape(-1)
        pred = lut[raw_pred[scored]]
        bad = int((pred == IGNORE_INDEX).sum())
        if bad:
            raise DataError(f"{pred_file}: {bad} scored voxels hold raw ids the SSC table ignores (write train ids "
                            "through learning_map_inv)")
        codes = (regions[scored] * k + pred) * k + target[scored]
        conf += np.bincount(codes, minlength=3 * k * k).reshape(3, k, k)
        if progress:
            progress(n + 1, len(jobs))
    boxes = {RANGES[1]: conf[1:].sum(axis=0), RANGES[0]: conf[2]}
    return Evaluation(len(jobs), ssc_scores(conf.sum(axis=0)), {r: ssc_scores(c) for r, c in boxes.items()},
                      tuple(table.names))


def scores_yaml(ev: Evaluation) -> dict[str, float]:
    """The official ``scores.txt`` keys (iou_completion, iou_mean, iou_<class>) and the range split's."""
    out = {"iou_completion": ev.scores["iou"], "iou_mean": ev.scores["miou"],
           "precision_completion": ev.scores["precision"], "recall_completion": ev.scores["recall"]}
    out.update({f"iou_{name}": v for name, v in zip(ev.names[1:], ev.scores["class_iou"])})
    for r, s in ev.ranges.items():
        out[f"iou_completion_{r:g}m"], out[f"iou_mean_{r:g}m"] = s["iou"], s["miou"]
    return out


__all__ = ["Evaluation", "RANGES", "evaluate_folder", "frames_of", "many", "plan_folder", "range_mask",
           "scores_yaml"]
