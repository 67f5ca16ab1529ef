"""Exact nearest neighbours at scene size: a k-d tree on the CPU (SciPy's ``cKDTree``), a blocked
distance search elsewhere. Never an M x N matrix at once; indices only (no gradient flows through
the search — callers gather the points they matched and differentiate through those)."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.geometry.knn import knn


def _check(query: Tensor, support: Tensor) -> None:
    if query.dim() != 2 or support.dim() != 2 or query.shape[1] != support.shape[1]:
        raise ValueError(f"nearest neighbours need (M, D) and (N, D) points, got {tuple(query.shape)} and "
                         f"{tuple(support.shape)}")
    if support.shape[0] == 0:
        raise ValueError("nearest neighbours: the support point set is empty")


def knn_indices(query: Tensor, support: Tensor, k: int) -> Tensor:
    """(M, k) int64 indices of the ``k`` nearest ``support`` points of each ``query`` point, nearest first."""
    _check(query, support)
    k = min(k, support.shape[0])
    if query.shape[0] == 0:
        return torch.zeros((0, k), dtype=torch.long, device=query.device)
    if query.device.type == "cpu":
        from scipy.spatial import cKDTree

        tree = cKDTree(support.detach().double().numpy())
        _, idx = tree.query(query.detach().double().numpy(), k=k, workers=-1)
        out = torch.from_numpy(idx).long()
        return out.view(-1, k)
    return knn(query.detach(), support.detach(), k)[1]


def nearest(query: Tensor, support: Tensor) -> Tensor:
    """(M,) int64 index of the nearest ``support`` point of each ``query`` point."""
    return knn_indices(query, support, 1)[:, 0]


def knn_excluding_self(points: Tensor, k: int) -> Tensor:
    """(M, k) indices of each point's ``k`` nearest *other* points (its own index never appears, even when
    another point sits at the same place)."""
    m = points.shape[0]
    if k >= m:
        raise ValueError(f"{k} neighbours of each point need more than {k} points, got {m}")
    idx = knn_indices(points, points, k + 1)
    own = idx == torch.arange(m, device=idx.device)[:, None]
    # drop the point's own column where it was found, else the farthest of the k + 1
    own[:, -1] |= ~own.any(dim=1)
    return idx[~own].view(m, k)


__all__ = ["knn_excluding_self", "knn_indices", "nearest"]
