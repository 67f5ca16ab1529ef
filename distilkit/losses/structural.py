"""ScoreLiDAR's structural loss (eq. 12-17): a scene-wise and a point-wise term between a generated scene
and its ground truth, and the curvature key points the point-wise term compares.

Point sets are (M, 3) tensors; the batched forms take a :class:`~distilkit.taps.PointCloud` (padded points
and lengths) and average the per-scene values. Nearest neighbours come from
:mod:`distilkit.geometry.nearest` (a k-d tree on the CPU, a blocked search elsewhere): no M x N matrix at
scene size. The released code differs from the paper here (seed_code.md §3.5): its scene-wise term is an
index-aligned MSE between two unordered sets (``legacy_index_aligned=True`` reproduces it), and its
key points are taken at the same flat indices of both clouds; distilkit follows the paper.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.geometry.nearest import knn_excluding_self, nearest
from distilkit.structures import PointCloud


def _points(x: Tensor, what: str) -> None:
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"{what} must be (M, 3) points, got {tuple(x.shape)}")
    if x.shape[0] == 0:
        raise ValueError(f"{what} is empty")


def _per_scene(fn, generated: Tensor | PointCloud, target: Tensor | PointCloud, *extra) -> Tensor:  # noqa: ANN001
    """``fn`` on one scene, or the mean of ``fn`` over the scenes of two point-cloud batches."""
    if isinstance(generated, PointCloud) or isinstance(target, PointCloud):
        if not (isinstance(generated, PointCloud) and isinstance(target, PointCloud)):
            raise TypeError("give both point sets as (M, 3) tensors or both as PointClouds")
        if len(generated.lengths) != len(target.lengths):
            raise ValueError(f"{len(generated.lengths)} generated scenes but {len(target.lengths)} targets")
        per = [fn(generated.cloud(b), target.cloud(b), *(e[b] for e in extra)) for b in range(len(target.lengths))]
        return torch.stack(per).mean()
    return fn(generated, target, *extra)


def _scene_wise(generated: Tensor, target: Tensor, legacy: bool, reduction: str = "mean") -> Tensor:
    _points(generated, "generated")
    _points(target, "target")
    if legacy:  # the released code: F.mse_loss(pcd_full, x0), i.e. point i against point i, per coordinate
        if generated.shape != target.shape:
            raise ValueError(f"legacy_index_aligned needs equal sizes, got {tuple(generated.shape)} and "
                             f"{tuple(target.shape)}")
        return F.mse_loss(generated, target)
    if reduction not in ("mean", "sum"):
        raise ValueError(f"scene_wise reduction must be 'mean' or 'sum', got {reduction!r}")
    idx = nearest(generated, target)
    sq = (generated - target[idx]).pow(2)
    return sq.mean() if reduction == "mean" else sq.sum(dim=1).mean()


def scene_wise(generated: Tensor | PointCloud, target: Tensor | PointCloud,
               legacy_index_aligned: bool = False, reduction: str = "mean") -> Tensor:
    """ScoreLiDAR eq. 12 as the paper describes it: the squared distance of each generated point to its nearest
    target point (the target carries no gradient), averaged over points and coordinates (``reduction="mean"``,
    the per-element MSE the released code's lambda = 0.5 was tuned with) or summed over xyz (``"sum"``, eq. 12's
    squared norm: 3x the mean). ``legacy_index_aligned=True`` is the released code's ``F.mse_loss(target,
    generated)`` between index-aligned points."""
    return _per_scene(lambda g, t: _scene_wise(g, t, legacy_index_aligned, reduction), generated, target)


def curvature(points: Tensor, k: int = 180, chunk: int = 16384) -> Tensor:
    """ScoreLiDAR eq. 13-15 for every point: the covariance (1/k) of its k nearest other points about their
    centroid, and kappa = lambda_min / sum(lambda) of its eigenvalues (0 where the neighbourhood is a point).
    Computed in float64, in chunks of ``chunk`` points; returns (M,) in the points' dtype."""
    _points(points, "points")
    nbr = knn_excluding_self(points, k)
    pts = points.detach().double()
    out = []
    for start in range(0, points.shape[0], chunk):
        p = pts[nbr[start:start + chunk]]  # (c, k, 3)
        centred = p - p.mean(dim=1, keepdim=True)
        cov = centred.transpose(1, 2) @ centred / k
        lam = torch.linalg.eigvalsh(cov)  # ascending
        total = lam.sum(dim=1)
        out.append(torch.where(total > 0, lam[:, 0].clamp_min(0) / total.clamp_min(1e-300), torch.zeros_like(total)))
    return torch.cat(out).to(points.dtype)


def select_keypoints(points: Tensor, k: int = 180, sample_ratio: float = 0.1, keep_ratio: float = 1.0 / 3.0,
                     generator: torch.Generator | None = None) -> Tensor:
    """ScoreLiDAR's key points (§4.2, appendix A.3): a random ``sample_ratio`` of the points, then the
    ``keep_ratio`` of those with the largest curvature (eq. 15, neighbours within the sample). Returns int64
    indices into ``points``, by decreasing curvature. ``k`` is capped at the sample size minus one."""
    _points(points, "points")
    if not (0 < sample_ratio <= 1 and 0 < keep_ratio <= 1):
        raise ValueError(f"sample_ratio and keep_ratio must lie in (0, 1], got {sample_ratio} and {keep_ratio}")
    m = points.shape[0]
    n = max(2, round(m * sample_ratio))
    if n > m:
        raise ValueError(f"key points need at least 2 points, got {m}")
    sample = torch.randperm(m, generator=generator)[:n].to(points.device)
    kappa = curvature(points[sample], min(k, n - 1))
    keep = max(1, round(n * keep_ratio))
    return sample[torch.topk(kappa, keep, sorted=True).indices]


def _point_wise(generated: Tensor, target: Tensor, keypoints: Tensor) -> Tensor:
    _points(generated, "generated")
    _points(target, "target")
    key = target[keypoints].detach()
    matched = generated[nearest(key, generated)]  # the generated point closest to each key point
    d_target = torch.cdist(key, key, compute_mode="donot_use_mm_for_euclid_dist")
    d_generated = torch.cdist(matched, matched, compute_mode="donot_use_mm_for_euclid_dist")
    return (d_target - d_generated).pow(2).mean()


def point_wise(generated: Tensor | PointCloud, target: Tensor | PointCloud,
               keypoints: Tensor | list[Tensor]) -> Tensor:
    """ScoreLiDAR eq. 16: the mean squared difference between the Euclidean distance matrix of the target's
    key points (``keypoints``: indices into ``target``, as :func:`select_keypoints` returns them; a list of
    them for a batch) and that of each key point's nearest generated point. The n x n matrices are of key
    points only (n << M)."""
    extra = (keypoints,) if isinstance(target, PointCloud) else ()
    if extra:
        return _per_scene(_point_wise, generated, target, keypoints)
    return _point_wise(generated, target, keypoints)  # type: ignore[arg-type]


def structural(generated: Tensor | PointCloud, target: Tensor | PointCloud, keypoints: Tensor | list[Tensor],
               lambda_scene: float = 0.5, lambda_point: float = 0.01) -> Tensor:
    """ScoreLiDAR eq. 17: lambda_scene * scene_wise + lambda_point * point_wise."""
    return lambda_scene * scene_wise(generated, target) + lambda_point * point_wise(generated, target, keypoints)


__all__ = ["curvature", "point_wise", "scene_wise", "select_keypoints", "structural"]
