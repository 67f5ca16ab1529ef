"""Scene-completion metrics for point clouds, in LiDiff's conventions (seed_code.md §3.4).

* :func:`chamfer_distance` — (mean_gt NN(gt -> pred) + mean_pred NN(pred -> gt)) / 2, Euclidean;
* :func:`jsd_bev` — the Jensen-Shannon *distance* (sqrt of the divergence, natural log) between bird's-eye
  histograms: 0.5 m voxels over [-50, 50]^3, occupancy clipped to {0, 1}, summed over z;
* :func:`voxel_confusion` — occupied-voxel TP / FP / FN at one voxel size, from sets of unique voxel keys
  (the fixed LiDiff IoU without its 1000^3 histogram);
* :func:`precision_recall_curves` and :func:`auc` — the fraction of points within tau of the other cloud
  for tau in 5-10 cm, and the Simpson-rule area normalised by a perfect predictor's.

Point sets are (M, 3) tensors; nearest neighbours come from :mod:`distilkit.geometry.nearest`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from distilkit.geometry.nearest import nearest


def _nn_dist(query: Tensor, support: Tensor) -> Tensor:
    q, s = query.detach().double(), support.detach().double()
    return (q - s[nearest(q, s)]).norm(dim=1)


def chamfer_distance(pred: Tensor, gt: Tensor) -> float:
    """LiDiff's Chamfer distance: the mean of the two directional mean Euclidean NN distances."""
    return float((_nn_dist(gt, pred).mean() + _nn_dist(pred, gt).mean()) / 2)


def _voxel_keys(points: Tensor, resolution: float, max_range: float) -> Tensor:
    """(V, 3) unique voxel indices of the points inside [-max_range, max_range]^3 (the upper edge included,
    as ``np.histogramdd`` does)."""
    bins = int(round(2 * max_range / resolution))
    p = points.detach().double()
    inside = ((p >= -max_range) & (p <= max_range)).all(dim=1)
    idx = torch.floor((p[inside] + max_range) / resolution).long().clamp_(0, bins - 1)
    return torch.unique(idx, dim=0)


def _bev(points: Tensor, resolution: float, max_range: float) -> tuple[Tensor, Tensor]:
    """Occupied BEV cells (C, 2) and the number of occupied voxels in each column (C,)."""
    vox = _voxel_keys(points, resolution, max_range)
    cells, counts = torch.unique(vox[:, :2], dim=0, return_counts=True)
    return cells, counts.double()


def jsd_bev(pred: Tensor, gt: Tensor, resolution: float = 0.5, max_range: float = 50.0) -> float:
    """LiDiff's BEV Jensen-Shannon distance (``scipy.spatial.distance.jensenshannon`` of the two normalised
    column-occupancy histograms); 0 for identical occupancy, at most sqrt(ln 2)."""
    p_cells, p_counts = _bev(pred, resolution, max_range)
    q_cells, q_counts = _bev(gt, resolution, max_range)
    if p_counts.sum() == 0 or q_counts.sum() == 0:
        raise ValueError("jsd_bev: a point cloud has no point inside the histogram range")
    cells, inv = torch.unique(torch.cat([p_cells, q_cells]), dim=0, return_inverse=True)
    p = torch.zeros(len(cells), dtype=torch.float64).index_add_(0, inv[: len(p_cells)], p_counts)
    q = torch.zeros(len(cells), dtype=torch.float64).index_add_(0, inv[len(p_cells):], q_counts)
    p, q = p / p.sum(), q / q.sum()
    m = (p + q) / 2

    def kl(a: Tensor) -> Tensor:
        keep = a > 0
        return (a[keep] * torch.log(a[keep] / m[keep])).sum()

    return math.sqrt(max(float((kl(p) + kl(q)) / 2), 0.0))


def voxel_confusion(pred: Tensor, gt: Tensor, voxel_size: float, max_range: float = 50.0) -> tuple[int, int, int]:
    """Occupied voxels at ``voxel_size`` inside [-max_range, max_range]^3: (TP, FP, FN) of ``pred`` against
    ``gt``. IoU over a data set is sum TP / (sum TP + sum FP + sum FN)."""
    bins = int(round(2 * max_range / voxel_size))
    key = lambda v: (v[:, 0] * bins + v[:, 1]) * bins + v[:, 2]  # noqa: E731
    p = key(_voxel_keys(pred, voxel_size, max_range))
    g = key(_voxel_keys(gt, voxel_size, max_range))
    tp = int(torch.isin(p, g).sum())
    return tp, len(p) - tp, len(g) - tp


DEFAULT_THRESHOLDS = tuple(float(t) for t in torch.linspace(0.05, 0.10, 100, dtype=torch.float64))


def precision_recall_curves(pred: Tensor, gt: Tensor,
                            thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS) -> tuple[Tensor, Tensor]:
    """Per threshold tau: precision = share of predicted points within tau of the ground truth, recall =
    share of ground-truth points within tau of the prediction (float64 (T,) each)."""
    tau = torch.tensor(thresholds, dtype=torch.float64)
    d_pred, d_gt = _nn_dist(pred, gt), _nn_dist(gt, pred)
    precision = (d_pred[None, :] < tau[:, None]).double().mean(dim=1)
    recall = (d_gt[None, :] < tau[:, None]).double().mean(dim=1)
    return precision, recall


def auc(curve: Tensor, thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS) -> float:
    """Simpson-rule area under ``curve`` over the thresholds, divided by that of a perfect predictor (1 everywhere)."""
    from scipy.integrate import simpson

    x = list(thresholds)
    return float(simpson(curve.double().numpy(), x=x) / simpson([1.0] * len(x), x=x))


__all__ = ["DEFAULT_THRESHOLDS", "auc", "chamfer_distance", "jsd_bev", "precision_recall_curves", "voxel_confusion"]
