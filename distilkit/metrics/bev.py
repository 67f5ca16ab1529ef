"""Bird's-eye views of one scene for run reports: the class seen from above in a voxel grid, the points of
a cloud. They feed :meth:`distilkit.metrics.base.Metric.preview`."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

MAX_POINTS = 60_000  # per panel: enough to see a scene, small enough for preview.npz


def top_class(labels: Tensor, ignore: int) -> np.ndarray:
    """(X, Y, Z) class ids -> (X, Y): the class of the highest voxel that is neither empty (0) nor ``ignore``;
    -1 where the column holds none."""
    occupied = (labels != 0) & (labels != ignore)
    z = labels.shape[-1]
    height = torch.where(occupied, torch.arange(z, device=labels.device), torch.full_like(labels, -1)).amax(dim=-1)
    top = labels.gather(-1, height.clamp_min(0).unsqueeze(-1)).squeeze(-1)
    return torch.where(height >= 0, top, torch.full_like(top, -1)).cpu().numpy().astype(np.int16)


def thin(points: Tensor, limit: int = MAX_POINTS) -> np.ndarray:
    """At most ``limit`` points (an even stride, so the view stays the same from run to run), float32 (N, 3)."""
    pts = points[:, :3].detach().float().cpu()
    if len(pts) > limit:
        pts = pts[torch.linspace(0, len(pts) - 1, limit).long()]
    return pts.numpy()


__all__ = ["MAX_POINTS", "thin", "top_class"]
