"""Statistics of a training split that terms need (class frequencies for class weights)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from distilkit.data.classes import IGNORE_INDEX, SCRIBBLE_UNLABELLED

_CACHE = "_distilkit_label_counts"


def _own_cache(dataset: Any) -> dict[Any, tuple[Tensor, Tensor]] | None:
    """The counts cached on ``dataset`` itself, never on what it wraps: a wrapper that forwards attribute lookups (a
    label overlay, a split) must not answer with the counts of the data beneath it, whose labels differ."""
    own = getattr(dataset, "__dict__", None)
    if own is None:
        return None
    return own.setdefault(_CACHE, {})


def label_counts(dataset: Any, num_classes: int, field: str = "voxel_label") -> tuple[Tensor, Tensor]:
    """(voxel counts (K,), point counts (K,)) of the labels a stage trains on.

    ``field`` is the voxel labels counted: ``voxel_label`` (the samples' own, or a label overlay's pseudo-labels)
    over its valid voxels, or ``scribble`` over the scribbled voxels only (empty 0, unlabelled 254 and ignored 255
    left out: the scribble setting never reads dense labels). Point counts are of ``point_label`` where the data has
    points. Counted once per dataset object (the split does not change during a run) and kept on that object.
    """
    cache = _own_cache(dataset)
    key = (field, num_classes)
    if cache is not None and key in cache:
        return cache[key]
    voxel = np.zeros(num_classes, np.int64)
    point = np.zeros(num_classes, np.int64)
    for i in range(len(dataset)):
        s = dataset[i]
        if field not in s:
            raise KeyError(f"label counts: the training samples have no {field!r} field")
        vl = np.asarray(s[field]).ravel()
        keep = vl != IGNORE_INDEX
        if field == "scribble":
            keep &= (vl != 0) & (vl != SCRIBBLE_UNLABELLED)
        elif "invalid" in s:
            keep &= ~np.asarray(s["invalid"]).ravel().astype(bool)
        voxel += np.bincount(vl[keep].astype(np.int64), minlength=num_classes)[:num_classes]
        if "point_label" in s:  # camera data has no points
            pl = np.asarray(s["point_label"]).astype(np.int64)
            point += np.bincount(pl[pl < num_classes], minlength=num_classes)[:num_classes]
    out = (torch.from_numpy(voxel), torch.from_numpy(point))
    if cache is not None:
        cache[key] = out
    return out
