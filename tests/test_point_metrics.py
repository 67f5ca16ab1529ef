"""Point-cloud completion metrics in LiDiff's conventions, against numpy/scipy computed another way."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.integrate import simpson
from scipy.spatial.distance import jensenshannon

from distilkit.metrics import auc, chamfer_distance, jsd_bev, precision_recall_curves, voxel_confusion
from distilkit.metrics.points import emd, jsd_3d


def scene(m: int, seed: int, spread: float = 20.0) -> torch.Tensor:
    g = np.random.default_rng(seed)
    return torch.from_numpy(g.normal(0, spread, size=(m, 3)))


def brute_nn_dist(q: np.ndarray, s: np.ndarray) -> np.ndarray:
    return np.sqrt(((q[:, None] - s[None]) ** 2).sum(-1)).min(1)


def test_chamfer_is_the_mean_of_both_directions_halved(device) -> None:
    p, g = scene(300, 0), scene(400, 1)
    want = (brute_nn_dist(g.numpy(), p.numpy()).mean() + brute_nn_dist(p.numpy(), g.numpy()).mean()) / 2
    assert chamfer_distance(p.to(device), g.to(device)) == pytest.approx(want, rel=1e-12)
    assert chamfer_distance(g, g) == 0


def test_jsd_bev_matches_lidiffs_histogram_and_scipy() -> None:
    p, g = scene(2000, 2), scene(2500, 3)
    p[:5] = torch.tensor([60.0, 0, 0])  # out of range: not counted
    p[5] = torch.tensor([50.0, 50.0, 50.0])  # on the upper edge: counted, as np.histogramdd does

    def bev(x: np.ndarray) -> np.ndarray:
        h, _ = np.histogramdd(x, bins=200, range=[(-50, 50)] * 3)
        return np.clip(h, 0, 1).sum(2).ravel()

    hg, hp = bev(g.numpy()), bev(p.numpy())
    want = jensenshannon(hg / hg.sum(), hp / hp.sum())
    assert jsd_bev(p, g) == pytest.approx(float(want), rel=1e-9)
    assert jsd_bev(g, g) == 0.0


def test_voxel_iou_counts_equal_dense_occupancy_histograms(device) -> None:
    p, g = scene(3000, 4, 8.0), scene(3000, 5, 8.0)
    for size in (0.5, 2.0):
        bins = int(100 / size)
        hp = np.histogramdd(p.numpy(), bins=bins, range=[(-50, 50)] * 3)[0] > 0
        hg = np.histogramdd(g.numpy(), bins=bins, range=[(-50, 50)] * 3)[0] > 0
        want = (int((hp & hg).sum()), int((hp & ~hg).sum()), int((~hp & hg).sum()))
        assert voxel_confusion(p.to(device), g.to(device), size) == want


def test_jsd_3d_is_the_unclipped_point_count_histograms_distance() -> None:
    p, g = scene(2000, 12), scene(2500, 13)
    p[:300] = p[:1].clone()  # 300 points in one voxel: counted 300 times (no clipping)
    p[300] = torch.tensor([60.0, 0, 0])  # out of range: dropped

    def counts(x: np.ndarray) -> np.ndarray:
        h, _ = np.histogramdd(x, bins=200, range=[(-50, 50)] * 3)
        return h.ravel()

    cg, cp = counts(g.numpy()), counts(p.numpy())
    used = (cg > 0) | (cp > 0)  # of the 200^3 bins: those empty in both add 0 to the distance
    want = jensenshannon(cg[used] / cg.sum(), cp[used] / cp.sum())
    got = jsd_3d(p, g)
    assert got == pytest.approx(float(want), rel=1e-9)
    assert got != pytest.approx(jsd_bev(p, g))


def test_the_rounded_iou_is_lidiffs_histogram_of_rounded_indices() -> None:
    """LiDiff before its June 2025 fix (and ScoreLiDAR): np.round(p / v) histogrammed over [-50, 50] in index units."""
    p, g = scene(3000, 14, 12.0), scene(3000, 15, 12.0)
    p[0] = torch.tensor([25.0, 0.0, 0.0])  # index 50 at 0.5 m: the upper edge, counted
    p[1] = torch.tensor([25.3, 0.0, 0.0])  # index 51: outside
    size = 0.5
    bins = int(2 * 50 / size)
    hp = np.histogramdd(np.round(p.numpy() / size), bins=bins, range=[(-50, 50)] * 3)[0] > 0
    hg = np.histogramdd(np.round(g.numpy() / size), bins=bins, range=[(-50, 50)] * 3)[0] > 0
    want = (int((hp & hg).sum()), int((hp & ~hg).sum()), int((~hp & hg).sum()))
    assert voxel_confusion(p, g, size, rounded=True) == want
    assert voxel_confusion(p, g, size, rounded=True) != voxel_confusion(p, g, size)


def test_emd_is_the_optimal_matching_of_equal_subsamples() -> None:
    from itertools import permutations

    a, b = scene(6, 16, 3.0), scene(6, 17, 3.0)
    d = np.sqrt(((a.numpy()[:, None] - b.numpy()[None]) ** 2).sum(-1))
    want = min(d[np.arange(6), list(perm)].mean() for perm in permutations(range(6)))
    assert emd(a, b) == pytest.approx(want, rel=1e-12)
    assert emd(a, a) == 0.0
    big, other = scene(3000, 18, 3.0), scene(2500, 19, 3.0)  # larger than the draws: subsampled
    assert emd(big, other, points=256) == emd(big, other, points=256)  # a seeded draw: repeatable
    assert emd(big, other, points=8) != emd(big, other, points=16)


def test_precision_recall_auc_over_5_to_10_cm() -> None:
    g = scene(500, 6, 2.0)
    p = g + torch.from_numpy(np.random.default_rng(7).normal(0, 0.04, size=g.shape))
    tau = tuple(np.linspace(0.05, 0.10, 100))
    precision, recall = precision_recall_curves(p, g)
    d_p, d_g = brute_nn_dist(p.numpy(), g.numpy()), brute_nn_dist(g.numpy(), p.numpy())
    assert np.allclose(precision.numpy(), [(d_p < t).mean() for t in tau])
    assert np.allclose(recall.numpy(), [(d_g < t).mean() for t in tau])
    assert auc(precision) == pytest.approx(simpson(precision.numpy(), x=tau) / (tau[-1] - tau[0]), rel=1e-12)
    assert auc(torch.ones(100, dtype=torch.float64)) == pytest.approx(1.0)
    assert 0 < auc(precision) < 1


def _naive_lidiff_eval(preds: list[np.ndarray], gts: list[np.ndarray]) -> dict[str, float]:
    """LiDiff's eval_path.py written out with brute-force distances (float64): predictions cut to a 3-D range
    < 50 m, CD per scene, per-scene F per threshold averaged over scenes, then Simpson's normalised area."""
    from scipy.integrate import simpson

    tau = np.linspace(0.05, 0.10, 100)
    cds, ps, rs, fs = [], [], [], []
    for pred, gt in zip(preds, gts):
        pred = pred[np.sqrt((pred ** 2).sum(1)) < 50.0]
        d = np.sqrt(((pred[:, None, :] - gt[None, :, :]) ** 2).sum(-1))
        d_pred, d_gt = d.min(1), d.min(0)
        cds.append((d_gt.mean() + d_pred.mean()) / 2)
        pr = np.array([(d_pred < t).mean() for t in tau])
        re = np.array([(d_gt < t).mean() for t in tau])
        ps.append(pr)
        rs.append(re)
        fs.append(np.where(pr + re > 0, 2 * pr * re / np.maximum(pr + re, 1e-300), 0.0))
    area = lambda c: simpson(np.mean(c, 0), x=tau) / simpson(np.ones(100), x=tau)  # noqa: E731
    return {"cd": float(np.mean(cds)), "precision": area(ps), "recall": area(rs), "fscore": area(fs)}


def test_the_registered_completion_metric_accumulates_like_lidiffs_evaluation() -> None:
    from distilkit.data.batch import Batch
    from distilkit.registry import METRICS
    from distilkit.taps import PointCloud

    cls = METRICS.get("completion")
    gts = [scene(400, 10, 5.0), scene(300, 11, 5.0)]
    preds = [g[:250] + 0.03 for g in gts]
    preds[0] = preds[0] + 0.05 * torch.randn(250, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    far = torch.tensor([[80.0, 0.0, 0.0], [30.0, 30.0, 30.0]], dtype=torch.float64)  # 3-D range 80 m, 52 m: dropped
    preds[1] = torch.cat([preds[1], far])
    gt = PointCloud.from_list([g.float() for g in gts])
    batch = Batch({}, {"scene_eval": gt.points, "scene_eval_lengths": gt.lengths}, {"size": 2})
    metric = cls(None)
    metric.update(PointCloud.from_list([p.float() for p in preds]), batch)
    got = metric.compute()
    want = _naive_lidiff_eval([p.float().double().numpy() for p in preds], [g.float().double().numpy() for g in gts])
    for key in ("cd", "precision", "recall", "fscore"):
        assert got[key] == pytest.approx(want[key], rel=1e-9), key
    kept = [preds[0], preds[1][:-2]]
    # F is the mean of per-scene F, not F of the mean precision and recall (which differs here)
    p_mean, r_mean = (torch.stack([precision_recall_curves(p.float().double(), g.float().double())[i]
                                   for p, g in zip(kept, gts)]).mean(0) for i in (0, 1))
    assert abs(auc(2 * p_mean * r_mean / (p_mean + r_mean)) - got["fscore"]) > 1e-4
    conf = [voxel_confusion(p.float().double(), g.float().double(), 0.2) for p, g in zip(kept, gts)]
    tp, fp, fn = (sum(c[i] for c in conf) for i in range(3))
    assert got["iou_20cm"] == pytest.approx(tp / (tp + fp + fn))
    assert set(got) == set(cls.KEYS) and cls.LOWER_IS_BETTER == {"cd", "jsd", "jsd_3d"}
    assert got["jsd_3d"] == pytest.approx(np.mean([jsd_3d(p, g) for p, g in zip(kept, gts)]))
    rounded = [voxel_confusion(p.float().double(), g.float().double(), 0.2, rounded=True) for p, g in zip(kept, gts)]
    tp, fp, fn = (sum(c[i] for c in rounded) for i in range(3))
    assert got["iou_20cm_rounded"] == pytest.approx(tp / (tp + fp + fn))
