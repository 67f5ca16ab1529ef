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


def _write(root, pred_root, seed: int, sequences: tuple[str, ...] = ("08", "09")) -> None:
    rng = np.random.default_rng(seed)
    for seq in sequences:
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


def naive_evaluate_completion(root, pred_root, sequences, box: int | None = None,
                              learning_map: dict[int, int] = LEARNING_MAP, k: int = 20,
                              boxes: tuple[int | None, ...] | None = None):
    """evaluate_completion.py written out: LUT both, mask = target != 255 and not invalid, one 20 x 20 confusion
    over every frame (rows prediction), class IoU with 1e-15, completion scores with float32 eps; ``box``: VoxFormer's
    range box (the target outside set to 255). ``boxes``: the scores of each of these boxes from one reading of the
    files (a dict by box)."""
    lut = np.full(400, 255, np.int64)  # ids missing from the map are ignored, as the official LUT's zeros become 255
    for raw, v in learning_map.items():
        lut[raw] = v if v != 0 or raw == 0 else 255
    which = (box,) if boxes is None else boxes
    confs = {b: np.zeros((k, k), np.int64) for b in which}
    for seq in sequences:
        for f in sorted((root / "sequences" / seq / "voxels").glob("*.label")):
            full = lut[np.fromfile(f, np.uint16).astype(np.int64)].reshape(SHAPE)
            invalid = np.unpackbits(np.fromfile(f.with_suffix(".invalid"), np.uint8)).reshape(SHAPE)
            pred = lut[np.fromfile(pred_root / "sequences" / seq / "predictions" / f.name, np.uint16).astype(np.int64)]
            for b, conf in confs.items():
                target = full.copy()
                if b == 256:
                    target[128:], target[:, :64], target[:, 192:] = 255, 255, 255
                elif b == 128:
                    target[64:], target[:, :96], target[:, 160:] = 255, 255, 255
                mask = (target.reshape(-1) != 255) & (invalid.reshape(-1) != 1)
                np.add.at(conf, (pred[mask], target.reshape(-1)[mask]), 1)
    eps = np.finfo(np.float32).eps
    scores = {}
    for b, conf in confs.items():
        tp = np.diag(conf).astype(np.float64)
        iou = tp / (tp + (conf.sum(1) - tp) + (conf.sum(0) - tp) + 1e-15)
        scores[b] = {"iou_mean": float(iou[1:].mean()),
                     "iou_completion": float(conf[1:, 1:].sum() / (conf.sum() - conf[0, 0])),
                     "precision_completion": float(conf[1:, 1:].sum() / (conf[1:, :].sum() + eps)),
                     "recall_completion": float(conf[1:, 1:].sum() / (conf[:, 1:].sum() + eps)),
                     "class_iou": iou[1:].tolist()}
    return scores if boxes is not None else scores[box]


def test_eval_equals_the_official_script_on_random_data(tmp_path, capsys) -> None:
    root, preds = tmp_path / "kitti", tmp_path / "preds"
    _write(root, preds, 0)
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--sequences", "08", "09"]) == 0
    got = yaml.safe_load((preds / "scores.txt").read_text())
    boxes = naive_evaluate_completion(root, preds, ["08", "09"], boxes=(None, 256, 128))
    want = boxes[None]
    for key, value in want.items():
        if key != "class_iou":
            assert got[key] == pytest.approx(value, rel=1e-12, abs=1e-15), key
    assert got["iou_car"] == pytest.approx(want["class_iou"][0], rel=1e-12)
    assert got["iou_other-vehicle"] == 0.0 < got["iou_car"]  # never predicted: counts 0 in the mean
    for r, box in ((25.6, 256), (12.8, 128)):
        ranged = boxes[box]
        assert got[f"iou_mean_{r:g}m"] == pytest.approx(ranged["iou_mean"], rel=1e-12)
        assert got[f"iou_completion_{r:g}m"] == pytest.approx(ranged["iou_completion"], rel=1e-12)
    assert "4 frames" in capsys.readouterr().out
    # the default split is the official validation split (08 only)
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--out", str(tmp_path / "v.txt")]) == 0
    got = yaml.safe_load((tmp_path / "v.txt").read_text())
    assert got["iou_mean"] == pytest.approx(naive_evaluate_completion(root, preds, ["08"])["iou_mean"], rel=1e-12)


def test_eval_names_what_is_missing_or_malformed(tmp_path, capsys) -> None:
    root, preds = tmp_path / "kitti", tmp_path / "preds"
    _write(root, preds, 1, sequences=("09",))  # the one sequence evaluated here
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


def test_eval_of_a_semanticposs_folder_uses_its_class_table(tmp_path) -> None:
    """SemanticPOSS (JS3C-Net's labels): 11 classes + empty, trashcan (14) and cone/stone (16) ignored."""
    from distilkit.data.classes import POSS_LEARNING_MAP, POSS_LEARNING_MAP_INV

    rng = np.random.default_rng(2)
    root, preds = tmp_path / "poss", tmp_path / "preds"
    raw_ids = np.array(sorted(POSS_LEARNING_MAP), np.uint16)
    to_raw = np.array([POSS_LEARNING_MAP_INV[t] for t in range(12)], np.uint16)
    for d in (root / "sequences" / "02" / "voxels", preds / "sequences" / "02" / "predictions"):
        d.mkdir(parents=True)
    gt = np.where(rng.random(SHAPE) < 0.7, 0, rng.choice(raw_ids, size=SHAPE)).astype(np.uint16)
    sk.write_voxel_labels(root / "sequences" / "02" / "voxels" / "000000.label", gt)
    sk.write_voxel_bits(root / "sequences" / "02" / "voxels" / "000000.invalid", rng.random(SHAPE) < 0.1)
    sk.write_voxel_labels(preds / "sequences" / "02" / "predictions" / "000000.label",
                          to_raw[rng.integers(0, 12, SHAPE)])
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--classes", "semanticposs"]) == 0
    got = yaml.safe_load((preds / "scores.txt").read_text())
    want = naive_evaluate_completion(root, preds, ["02"], learning_map=POSS_LEARNING_MAP, k=12)
    assert got["iou_mean"] == pytest.approx(want["iou_mean"], rel=1e-12)
    assert got["iou_completion"] == pytest.approx(want["iou_completion"], rel=1e-12)
    assert [got[f"iou_{n}"] for n in ("people", "ground")] == pytest.approx([want["class_iou"][0], want["class_iou"][10]])
    assert "iou_car" in got and "iou_road" not in got


def test_a_semanticposs_folder_reads_with_its_own_labels(tmp_path) -> None:
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticPossParams
    from distilkit.registry import DATASETS

    seq = tmp_path / "sequences" / "02"
    for sub in ("velodyne", "labels", "voxels"):
        (seq / sub).mkdir(parents=True)
    np.zeros((3, 4), np.float32).tofile(seq / "velodyne" / "000000.bin")
    sk.write_point_labels(seq / "labels" / "000000.label", np.array([4, 14, 22]), np.zeros(3, np.int64))
    raw = np.zeros(SHAPE, np.uint16)
    raw[0, 0, 0], raw[1, 0, 0], raw[2, 0, 0], raw[3, 0, 0] = 7, 14, 22, 5  # car, trashcan, ground, 2+-person
    sk.write_voxel_labels(seq / "voxels" / "000000.label", raw)
    params = DATASETS.entry("semanticposs-ssc").meta["params"](root=str(tmp_path))
    assert isinstance(params, SemanticPossParams) and params.sequences("val") == ["02"]
    ds = SemanticKittiDataset(params, "val")
    s = ds[0]
    assert s["voxel_label"][:4, 0, 0].tolist() == [3, 255, 11, 1] and s["point_label"].tolist() == [1, 0, 11]
    assert DATASETS.entry("semanticposs-ssc").meta["info"](params).num_classes == 12
    with pytest.raises(Exception, match="'road'"):
        DATASETS.entry("semanticposs-ssc").meta["params"](root=str(tmp_path), rectify_classes=["road"])
