"""Official SemanticKITTI SSC evaluation (``evaluate_completion.py``; data_metrics.md §1.8).

The confusion matrix has rows = prediction and columns = ground truth and is accumulated
over a whole split (never averaged per frame). Voxels whose target is ``ignore_index`` or
that are ``invalid`` are excluded.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor


def ssc_confusion(
    pred: Tensor,
    target: Tensor,
    num_classes: int,
    invalid: Tensor | None = None,
    ignore_index: int = 255,
) -> Tensor:
    """(K, K) int64 confusion matrix, ``conf[p, g]`` = #voxels predicted p with ground truth g.

    Args:
        pred: integer predictions, any shape, values in [0, K).
        target: integer ground truth of the same shape; ``ignore_index`` voxels are skipped.
        invalid: optional bool mask of the same shape; True voxels are skipped.
    """
    if pred.shape != target.shape:
        raise ValueError(f"ssc_confusion: pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
    mask = target != ignore_index
    if invalid is not None:
        if invalid.shape != target.shape:
            raise ValueError(f"ssc_confusion: invalid {tuple(invalid.shape)} does not match target {tuple(target.shape)}")
        mask &= ~invalid.bool()
    p = pred[mask].long()
    g = target[mask].long()
    if p.numel() and (int(p.min()) < 0 or int(p.max()) >= num_classes):
        raise ValueError(f"ssc_confusion: predictions must lie in [0, {num_classes}), got range [{int(p.min())}, {int(p.max())}]")
    if g.numel() and (int(g.min()) < 0 or int(g.max()) >= num_classes):
        raise ValueError(f"ssc_confusion: targets must lie in [0, {num_classes}) or be {ignore_index}, got max {int(g.max())}")
    flat = torch.bincount(p * num_classes + g, minlength=num_classes * num_classes)
    return flat.reshape(num_classes, num_classes).to(torch.int64).cpu()


def ssc_scores(confusion: Tensor | np.ndarray) -> dict[str, Any]:
    """Official scores from a (K,K) confusion matrix (rows = prediction, columns = ground truth).

    Returns ``iou``, ``precision``, ``recall`` (class-agnostic completion: occupied = class >= 1),
    ``class_iou`` (list for classes 1..K-1; a class with no prediction and no ground truth scores 0)
    and ``miou`` (their mean), and ``class_voxels`` (the ground truth's voxels of classes 1..K-1: how often each is
    seen, which orders the classes of a per-class comparison).
    """
    conf = np.asarray(confusion, dtype=np.float64)
    if conf.ndim != 2 or conf.shape[0] != conf.shape[1]:
        raise ValueError(f"ssc_scores expects a square confusion matrix, got shape {conf.shape}")
    tp = np.diag(conf)
    fp = conf.sum(axis=1) - tp
    fn = conf.sum(axis=0) - tp
    class_iou = tp / (tp + fp + fn + 1e-15)
    eps = float(np.finfo(np.float32).eps)
    occ_tp = conf[1:, 1:].sum()
    precision = occ_tp / (conf[1:, :].sum() + eps)
    recall = occ_tp / (conf[:, 1:].sum() + eps)
    denom = conf.sum() - conf[0, 0]
    iou = occ_tp / denom if denom > 0 else 0.0
    return {
        "iou": float(iou),
        "precision": float(precision),
        "recall": float(recall),
        "class_iou": [float(v) for v in class_iou[1:]],
        "miou": float(class_iou[1:].mean()),
        "class_voxels": [int(v) for v in conf.sum(axis=0)[1:]],
    }


class SSCMetric:
    """Accumulates :func:`ssc_confusion` over batches and reports :func:`ssc_scores`."""

    def __init__(self, num_classes: int, ignore_index: int = 255) -> None:
        self.num_classes = num_classes
        self.ignore_index = ignore_index
        self.confusion = torch.zeros((num_classes, num_classes), dtype=torch.int64)

    def update(self, pred: Tensor, target: Tensor, invalid: Tensor | None = None) -> None:
        self.confusion += ssc_confusion(pred, target, self.num_classes, invalid, self.ignore_index)

    def compute(self) -> dict[str, Any]:
        return ssc_scores(self.confusion)
