"""Exact k-nearest neighbours by blocked distance computation (never an M x N matrix at once)."""

from __future__ import annotations

import torch
from torch import Tensor


def knn(query: Tensor, support: Tensor, k: int, block: int = 4096) -> tuple[Tensor, Tensor]:
    """k nearest ``support`` points (N,D) of each ``query`` point (M,D).

    Returns (distances (M,k) Euclidean, indices (M,k) int64), nearest first. Works in blocks
    of ``block`` queries so memory is O(block * N). If N < k the result has N columns.
    """
    if query.dim() != 2 or support.dim() != 2 or query.shape[1] != support.shape[1]:
        raise ValueError(f"knn expects (M,D) and (N,D), got {tuple(query.shape)} and {tuple(support.shape)}")
    k = min(k, support.shape[0])
    dists, idxs = [], []
    for start in range(0, query.shape[0], block):
        d = torch.cdist(query[start:start + block], support)
        val, idx = torch.topk(d, k, dim=1, largest=False, sorted=True)
        dists.append(val)
        idxs.append(idx)
    if not dists:
        return query.new_zeros((0, k)), torch.zeros((0, k), dtype=torch.long, device=query.device)
    return torch.cat(dists), torch.cat(idxs)
