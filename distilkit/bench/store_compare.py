"""How a teacher store's read-back outputs differ from the live teacher's (``distilkit bench teacher-store``): each
tap's largest absolute difference, and each distillation term's value computed with them against its value with the
live teacher's outputs (the same student outputs)."""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor


def mask_of(labels: Tensor, voxels: str, ignore: int) -> Tensor | None:
    """The voxels a masked layout keeps, as a store's build chooses them (None: every voxel)."""
    keep = labels != ignore
    return None if voxels == "all" else keep & (labels != 0) if voxels == "occupied" else keep


def difference(live: Any, read: Any, meta: dict[str, Any], mask: Tensor | None) -> float:
    """The largest absolute difference between a tap as read back and the live teacher's: sparse features' and
    points' values (inf where their coordinates or counts differ); a dense tap's, inside ``mask`` where the layout
    stored it masked, of its softmax over the classes where it stored the top-k."""
    from distilkit.structures import PointCloud, SparseVoxels

    if isinstance(live, SparseVoxels):
        if not torch.equal(live.coords.cpu(), read.coords.cpu()):
            return float("inf")
        a, b = live.feats.cpu().float(), read.feats.cpu().float()
    elif isinstance(live, PointCloud):
        if not torch.equal(live.lengths.cpu(), read.lengths.cpu()):
            return float("inf")
        n = int(live.lengths[0])
        a, b = live.points[0, :n].cpu().float(), read.points[0, :n].cpu().float()
    else:
        a, b = live[0].cpu().float(), read[0].cpu().float()
        if meta.get("topk"):
            a, b = a.softmax(0), b.softmax(0)
        if meta.get("masked") and mask is not None:
            a, b = a[:, mask], b[:, mask]
    return float((a - b).abs().max()) if a.numel() else 0.0


def values(trainer: Any, s_out: dict[str, Any], t_out: dict[str, Any], batch: Any) -> dict[str, float]:
    """Each distillation term's weighted value (float64 of its float32) given the student's and teacher's outputs."""
    with torch.no_grad():
        got = trainer.term_values(s_out, t_out, batch)
    return {key: float(v) for key, v in got.items() if key.startswith("kd_")}


def term_differences(sub: Any, read: list[dict[str, Any]]) -> dict[str, tuple[float, float]]:
    """Each term's largest absolute difference over the samples between its value with the read-back teacher
    outputs and with the live ones, and that difference relative to the live value's magnitude."""
    out: dict[str, tuple[float, float]] = {}  # ``read``: on the trainer's device, as the bench reads it
    for s_out, got, batch, live in zip(sub.student, read, sub.batches, sub.terms):
        for key, value in values(sub.trainer, s_out, got, batch).items():
            d = abs(value - live[key])
            old = out.get(key, (0.0, 0.0))
            out[key] = (max(old[0], d), max(old[1], d / abs(live[key]) if live[key] else (math.inf if d else 0.0)))
    return out


__all__ = ["difference", "mask_of", "term_differences", "values"]
