"""SSC confusion and scores against a naive per-voxel implementation of evaluate_completion.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from distilkit.metrics import SSCMetric, ssc_confusion, ssc_scores


def naive_confusion(pred, target, k, invalid=None, ignore=255):
    conf = np.zeros((k, k), np.int64)
    for i, (p, g) in enumerate(zip(pred.reshape(-1).tolist(), target.reshape(-1).tolist())):
        if g == ignore or (invalid is not None and invalid.reshape(-1)[i]):
            continue
        conf[p, g] += 1
    return conf


def naive_scores(conf):
    k = conf.shape[0]
    ious = []
    for c in range(1, k):
        tp = conf[c, c]
        fp = sum(conf[c, j] for j in range(k) if j != c)
        fn = sum(conf[j, c] for j in range(k) if j != c)
        ious.append(tp / (tp + fp + fn + 1e-15))
    tp = sum(conf[i, j] for i in range(1, k) for j in range(1, k))
    pred_occ = sum(conf[i, j] for i in range(1, k) for j in range(k))
    gt_occ = sum(conf[i, j] for i in range(k) for j in range(1, k))
    union = conf.sum() - conf[0, 0]
    eps = np.finfo(np.float32).eps
    return {"iou": tp / union, "precision": tp / (pred_occ + eps), "recall": tp / (gt_occ + eps),
            "miou": float(np.mean(ious)), "class_iou": ious}


def test_confusion_rows_are_predictions(device) -> None:
    g = torch.Generator().manual_seed(0)
    pred = torch.randint(0, 5, (2, 6, 5, 4), generator=g)
    target = torch.randint(0, 5, (2, 6, 5, 4), generator=g)
    target[0, 0] = 255
    invalid = torch.rand(2, 6, 5, 4, generator=g) < 0.2
    conf = ssc_confusion(pred.to(device), target.to(device), 5, invalid.to(device))
    assert conf.dtype == torch.int64
    assert np.array_equal(conf.cpu().numpy(), naive_confusion(pred.numpy(), target.numpy(), 5, invalid.numpy()))
    one = ssc_confusion(torch.tensor([3]), torch.tensor([1]), 5)
    assert one[3, 1] == 1 and one.sum() == 1


def test_scores_match_official_definitions() -> None:
    rng = np.random.default_rng(1)
    conf = rng.integers(0, 50, (6, 6))
    conf[4, :] = 0
    conf[:, 4] = 0  # a class never predicted nor present: IoU 0 and still averaged
    got = ssc_scores(conf)
    want = naive_scores(conf)
    for key in ("iou", "precision", "recall", "miou"):
        assert got[key] == pytest.approx(want[key], rel=1e-12)
    assert got["class_iou"] == pytest.approx(want["class_iou"], rel=1e-12)
    assert got["class_iou"][3] == 0.0 and len(got["class_iou"]) == 5


def test_metric_accumulates_over_split_not_per_frame(device) -> None:
    m = SSCMetric(3)
    a_pred, a_gt = torch.tensor([1, 1, 0, 2]), torch.tensor([1, 0, 0, 2])
    b_pred, b_gt = torch.tensor([2, 2]), torch.tensor([1, 1])
    m.update(a_pred.to(device), a_gt.to(device))
    m.update(b_pred.to(device), b_gt.to(device))
    conf = naive_confusion(torch.cat([a_pred, b_pred]).numpy(), torch.cat([a_gt, b_gt]).numpy(), 3)
    assert np.array_equal(m.confusion.cpu().numpy(), conf)
    assert m.compute()["miou"] == pytest.approx(naive_scores(conf)["miou"])


def test_out_of_range_prediction_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="predictions must lie in"):
        ssc_confusion(torch.tensor([7]), torch.tensor([1]), 5)
    with pytest.raises(ValueError, match="differ in shape"):
        ssc_confusion(torch.tensor([1, 2]), torch.tensor([1]), 5)
