"""Statistics of a training split that terms need (class frequencies for class weights)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from distilkit.data.classes import IGNORE_INDEX


def label_counts(dataset: Any, num_classes: int) -> tuple[Tensor, Tensor]:
    """(voxel counts (K,), point counts (K,)) over a dataset's valid voxels and labelled points.

    Counted once per dataset object and kept on it (the split does not change during a run).
    """
    cached = getattr(dataset, "_distilkit_label_counts", None)
    if cached is not None and cached[0].numel() == num_classes:
        return cached
    voxel = np.zeros(num_classes, np.int64)
    point = np.zeros(num_classes, np.int64)
    for i in range(len(dataset)):
        s = dataset[i]
        vl = np.asarray(s["voxel_label"]).ravel()
        inv = np.asarray(s["invalid"]).ravel().astype(bool)
        keep = ~inv & (vl != IGNORE_INDEX)
        voxel += np.bincount(vl[keep].astype(np.int64), minlength=num_classes)[:num_classes]
        if "point_label" in s:  # camera data has no points
            pl = np.asarray(s["point_label"]).astype(np.int64)
            point += np.bincount(pl[pl < num_classes], minlength=num_classes)[:num_classes]
    out = (torch.from_numpy(voxel), torch.from_numpy(point))
    try:
        dataset._distilkit_label_counts = out
    except AttributeError:
        pass
    return out
