"""`distilkit eval`: SemanticKITTI's official completion evaluation of a predictions folder, against a naive
re-implementation of evaluate_completion.py (and VoxFormer's range split) on random data."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from distilkit.cli import main
from distilkit.data import semantickitti as sk
from distilkit.data.classes import LEARNING_MAP, LEARNING_MAP_INV

SHAPE = (256, 256, 32)
RAW = np.array(sorted(LEARNING_MAP), dtype=np.uint16)  # every raw id, some mapping to ignore (52, 99, 1)
TO_TRAIN = np.zeros(400, np.int64)
TO_TRAIN[list(LEARNING_MAP)] = list(LEARNING_MAP.values())
TO_RAW = np.array([LEARNING_MAP_INV[t] for t in range(20)], np.uint16)


def _write(root, pred_root, seed: int) -> None:
    rng = np.random.default_rng(seed)
    for seq in ("08", "09"):
        gt_dir, pred_dir = root / "sequences" / seq / "voxels", pred_root / "sequences" / seq / "predictions"
        gt_dir.mkdir(parents=True)
        pred_dir.mkdir(parents=True)
        for frame in ("000000", "000005"):
            gt = np.where(rng.random(SHAPE) < 0.7, 0, rng.choice(RAW, size=SHAPE)).astype(np.uint16)
            sk.write_voxel_labels(gt_dir / f"{frame}.label", gt)
            sk.write_voxel_bits(gt_dir / f"{frame}.invalid", rng.random(SHAPE) < 0.2)
            # predictions: mostly the ground truth's train id written back as raw, some noise, no class 5
            train = TO_TRAIN[gt]
            train = np.where(rng.random(SHAPE) < 0.3, rng.integers(0, 20, SHAPE), train)
            train[train == 5] = 4
            raw_pred = TO_RAW[train]
            sk.write_voxel_labels(pred_dir / f"{frame}.label", raw_pred)


def naive_evaluate_completion(root, pred_root, sequences, box: int | None = None) -> dict[str, float]:
    """evaluate_completion.py written out: LUT both, mask = target != 255 and not invalid, one 20 x 20 confusion
    over every frame (rows prediction), class IoU with 1e-15, completion scores with float32 eps; ``box``: VoxFormer's
    range box (the target outside set to 255)."""
    lut = np.zeros(400, np.int64)
    for k, v in LEARNING_MAP.items():
        lut[k] = v if v != 0 or k == 0 else 255
    conf = np.zeros((20, 20), np.int64)
    for seq in sequences:
        for f in sorted((root / "sequences" / seq / "voxels").glob("*.label")):
            target = lut[np.fromfile(f, np.uint16).astype(np.int64)].reshape(SHAPE)
            if box == 256:
                target[128:], target[:, :64], target[:, 192:] = 255, 255, 255
            elif box == 128:
                target[64:], target[:, :96], target[:, 160:] = 255, 255, 255
            invalid = np.unpackbits(np.fromfile(f.with_suffix(".invalid"), np.uint8)).reshape(SHAPE)
            pred = lut[np.fromfile(pred_root / "sequences" / seq / "predictions" / f.name, np.uint16).astype(np.int64)]
            mask = (target.reshape(-1) != 255) & (invalid.reshape(-1) != 1)
            np.add.at(conf, (pred[mask], target.reshape(-1)[mask]), 1)
    tp = np.diag(conf).astype(np.float64)
    iou = tp / (tp + (conf.sum(1) - tp) + (conf.sum(0) - tp) + 1e-15)
    eps = np.finfo(np.float32).eps
    return {"iou_mean": float(iou[1:].mean()), "iou_completion": float(conf[1:, 1:].sum() / (conf.sum() - conf[0, 0])),
            "precision_completion": float(conf[1:, 1:].sum() / (conf[1:, :].sum() + eps)),
            "recall_completion": float(conf[1:, 1:].sum() / (conf[:, 1:].sum() + eps)), "iou_car": float(iou[1]),
            "iou_other-vehicle": float(iou[5])}


def test_eval_equals_the_official_script_on_random_data(tmp_path, capsys) -> None:
    root, preds = tmp_path / "kitti", tmp_path / "preds"
    _write(root, preds, 0)
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "08", "09"]) == 0
    got = yaml.safe_load((preds / "scores.txt").read_text())
    want = naive_evaluate_completion(root, preds, ["08", "09"])
    for key, value in want.items():
        assert got[key] == pytest.approx(value, rel=1e-12, abs=1e-15), key
    assert got["iou_other-vehicle"] == 0.0 < got["iou_car"]  # never predicted: counts 0 in the mean
    for r, box in ((25.6, 256), (12.8, 128)):
        ranged = naive_evaluate_completion(root, preds, ["08", "09"], box)
        assert got[f"iou_mean_{r:g}m"] == pytest.approx(ranged["iou_mean"], rel=1e-12)
        assert got[f"iou_completion_{r:g}m"] == pytest.approx(ranged["iou_completion"], rel=1e-12)
    assert "4 frames" in capsys.readouterr().out
    # the default split is the official validation split (08 only)
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--out", str(tmp_path / "v.txt")]) == 0
    got = yaml.safe_load((tmp_path / "v.txt").read_text())
    assert got["iou_mean"] == pytest.approx(naive_evaluate_completion(root, preds, ["08"])["iou_mean"], rel=1e-12)


def test_eval_names_what_is_missing_or_malformed(tmp_path, capsys) -> None:
    root, preds = tmp_path / "kitti", tmp_path / "preds"
    _write(root, preds, 1)
    f = preds / "sequences" / "09" / "predictions" / "000005.label"
    f.write_bytes(f.read_bytes()[:100])
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "09"]) == 2
    assert "000005.label: 50 voxels, expected 2,097,152" in capsys.readouterr().err
    f.unlink()
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "09"]) == 2
    assert "no prediction for this frame" in capsys.readouterr().err
    sk.write_voxel_labels(f, np.full(SHAPE, 52, np.uint16))  # other-structure: the SSC table ignores it
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "09"]) == 2
    assert "learning_map_inv" in capsys.readouterr().err
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "07"]) == 2
    assert "no sequences/07/voxels/" in capsys.readouterr().err
