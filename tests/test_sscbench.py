"""SSCBench-KITTI-360 (``sscbench-kitti360``): a folder in the benchmark's layout written by :mod:`_sscbench`, read
back, validated and scored by ``distilkit eval`` against an independent per-class count."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from _sscbench import CAM_TO_VELO, DRIVE, P_RECT, R_RECT, SHAPE, write_folder, write_prediction
from conftest import folder_recipe
from distilkit.cli import main
from distilkit.data.sscbench import SscbenchParams, read_train_ids, read_voxel_mask
from distilkit.data.sscbench_folder import SscbenchDataset, sscbench_check
from distilkit.errors import DataError

VALID = DRIVE.format(6)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("sscbench") / "KITTI-360"
    return root, write_folder(root)


def _effective(sample):
    """The target a sample scores: its labels with the voxels it marks invalid ignored (as the collate does)."""
    return np.where(sample["invalid"], 255, sample["voxel_label"])


def test_the_folder_reads_back_as_the_benchmarks_target(folder) -> None:
    root, frames = folder
    ds = SscbenchDataset(SscbenchParams(root=str(root)), "val")
    assert [ds.sample_id(i) for i in range(len(ds))] == [f"{VALID}/000000", f"{VALID}/000005"]
    for i, key in enumerate(ds.items):
        s, truth = ds[i], frames[key].truth
        assert s["voxel_label"].shape == SHAPE and np.array_equal(_effective(s), truth)
        scored_invalid = frames[key].invalid & (truth != 255)
        assert scored_invalid.any()  # occupied voxels marked invalid are kept (SSCBench's preprocess.py)
        # the input: the occupied voxels of .bin as points, each in its own voxel, labelled with its target
        idx = np.floor((s["points"][:, :3] - np.array([0.0, -25.6, -2.0])) / 0.2).astype(int)
        grid = np.zeros(SHAPE, bool)
        grid[tuple(idx.T)] = True
        assert np.array_equal(grid, frames[key].occupied_input) and len(idx) == grid.sum()
        expected = truth[tuple(idx.T)]
        assert np.array_equal(s["point_label"], np.where(expected == 255, 0, expected))
    pre = SscbenchDataset(SscbenchParams(root=str(root), targets="preprocess"), "val")[1]
    assert np.array_equal(_effective(pre), frames[(VALID, "000005")].truth)


def test_the_grid_coarsens_and_the_batch_has_the_targets(folder) -> None:
    from distilkit.registry import DATASETS

    root, frames = folder
    entry = DATASETS.entry("sscbench-kitti360")
    params = SscbenchParams(root=str(root), scale=4)
    info = entry.meta["info"](params)
    assert info.num_classes == 19 and info.grid.shape == (64, 64, 8) and info.class_names[7] == "road"
    ds = entry.obj(params, "val")
    batch = entry.meta["collate"]([ds[0], ds[1]])
    assert tuple(batch.targets["voxel_target"].shape) == (2, 64, 64, 8)
    truth = frames[(VALID, "000000")].truth.reshape(64, 4, 64, 4, 8, 4)
    all_ignored = (truth == 255).all(axis=(1, 3, 5))
    assert np.array_equal(batch.targets["voxel_target"][0].numpy() == 255, all_ignored)


def test_readers_take_both_mask_formats_and_name_bad_files(tmp_path) -> None:
    bits = np.random.default_rng(0).random(SHAPE) < 0.3
    bits.astype(np.uint8).tofile(tmp_path / "bytes.invalid")
    np.packbits(bits.reshape(-1)).tofile(tmp_path / "packed.invalid")
    assert np.array_equal(read_voxel_mask(tmp_path / "bytes.invalid", "invalid mask"), bits)
    assert np.array_equal(read_voxel_mask(tmp_path / "packed.invalid", "invalid mask"), bits)
    np.zeros(1000, np.uint8).tofile(tmp_path / "short.invalid")
    with pytest.raises(DataError, match=r"short.invalid: 1000 bytes, expected 2,097,152 .* or 262,144"):
        read_voxel_mask(tmp_path / "short.invalid", "invalid mask")
    np.save(tmp_path / "bad.npy", np.full(SHAPE, 19, np.uint8))
    with pytest.raises(DataError, match="not train ids 0..18 or 255"):
        read_train_ids(tmp_path / "bad.npy", 19)
    np.save(tmp_path / "small.npy", np.zeros((4, 4, 4), np.uint8))
    with pytest.raises(DataError, match=r"shape \(4, 4, 4\), expected \(256, 256, 32\)"):
        read_train_ids(tmp_path / "small.npy", 19)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match="not a readable .npy"):
        read_train_ids(tmp_path / "obj.npy", 19)


def test_the_class_table_is_kitti360_yaml() -> None:
    from distilkit.data.classes import ssc_lut
    from distilkit.data.sscbench import COLOURS, LEARNING_MAP, LEARNING_MAP_INV, NAMES

    assert len(NAMES) == 19 == len(COLOURS) and NAMES[17] == "other-structure" and NAMES[18] == "other-object"
    assert all(LEARNING_MAP[LEARNING_MAP_INV[c]] == c for c in range(19))
    bgr = {10: (245, 150, 100), 52: (0, 150, 255), 99: (255, 255, 50), 72: (80, 240, 150)}  # kitti360.yaml, BGR
    assert all(COLOURS[LEARNING_MAP[raw]] == tuple(reversed(v)) for raw, v in bgr.items())
    lut = ssc_lut(LEARNING_MAP)
    assert lut[0] == 0 and lut[71] == 255 and lut[31] == 255 and lut[13] == 5 and lut[60] == 7 and lut[52] == 17


def _said(capsys) -> str:
    """What the command printed (errors go to stderr), its lines joined."""
    said = capsys.readouterr()
    return " ".join((said.out + said.err).split())


def _recipe(tmp_path, root, **data):
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump(folder_recipe(root, dataset="sscbench-kitti360", scale=8, **data)))
    return path


def test_validate_passes_on_the_folder(folder, tmp_path, capsys) -> None:
    root, _ = folder
    assert main(["validate", str(_recipe(tmp_path, root, train=["00"])), "--no-memory"]) == 0
    assert "recipe.yaml: ok" in _said(capsys)


def test_validate_names_a_missing_drive_a_missing_file_and_a_wrong_size(folder, tmp_path, capsys) -> None:
    root, _ = folder
    assert main(["validate", str(_recipe(tmp_path, root)), "--no-memory"]) == 2  # the official train split
    assert "data_2d_raw/2013_05_28_drive_0002_sync: missing" in _said(capsys)
    broken = tmp_path / "broken"
    write_folder(broken, {0: ("000000",), 6: ("000000",), 9: ("000000",)}, images=False)
    np.zeros(100, np.uint8).tofile(broken / "data_2d_raw" / VALID / "voxels" / "000000.invalid")
    (broken / "data_2d_raw" / VALID / "voxels" / "000000.label").unlink()
    problem = sscbench_check(SscbenchParams(root=str(broken)), "val")
    assert "voxels/000000.invalid: 100 bytes, expected 2,097,152 or 262,144 (the invalid mask" in problem
    assert "voxels/000000.label: missing (uint16 voxel labels)" in problem
    shutil.rmtree(broken / "data_2d_raw" / DRIVE.format(9))
    assert main(["validate", str(_recipe(tmp_path, broken, train=["00"])), "--no-memory"]) == 2
    out = _said(capsys)
    assert "data_2d_raw/2013_05_28_drive_0009_sync: missing" in out and "000000.invalid: 100 bytes" in out


def _naive_scores(truths, preds, box=None):
    """Per-class counts in float64 straight from the definition: voxels whose target is 255 left out; IoU_c = tp /
    (tp + fp + fn), 0 for a class absent from both; completion: occupied = class > 0."""
    tp, fp, fn = np.zeros(19), np.zeros(19), np.zeros(19)
    otp = ofp = ofn = 0.0
    for t, p in zip(truths, preds):
        if box is not None:
            t, p = t[box], p[box]
        keep = t != 255
        t, p = t[keep].astype(np.int64), p[keep].astype(np.int64)
        for c in range(19):
            tp[c] += float(np.sum((t == c) & (p == c)))
            fp[c] += float(np.sum((t != c) & (p == c)))
            fn[c] += float(np.sum((t == c) & (p != c)))
        otp += float(np.sum((t > 0) & (p > 0)))
        ofp += float(np.sum((t == 0) & (p > 0)))
        ofn += float(np.sum((t > 0) & (p == 0)))
    iou = [tp[c] / (tp[c] + fp[c] + fn[c]) if tp[c] + fp[c] + fn[c] else 0.0 for c in range(1, 19)]
    return {"iou": otp / (otp + ofp + ofn), "precision": otp / (otp + ofp), "recall": otp / (otp + ofn),
            "class_iou": iou, "miou": float(np.mean(iou))}


def test_eval_of_predictions_in_its_layout_gives_an_independent_count(folder, tmp_path) -> None:
    root, frames = folder
    rng = np.random.default_rng(7)
    truths, preds = [], []
    for n, frame in enumerate(("000000", "000005")):
        truth = frames[(VALID, frame)].truth
        pred = np.where(truth == 255, rng.integers(0, 19, SHAPE), truth)  # anything where nothing is scored
        flip = rng.random(SHAPE) < 0.05
        pred[flip] = rng.integers(0, 19, int(flip.sum()))
        pred[pred == 3] = 0  # one class never predicted
        write_prediction(tmp_path / "preds", VALID, frame, pred, raw=n == 1, seed=n)  # one .npy, one raw .label
        truths.append(truth)
        preds.append(pred)
    out = tmp_path / "scores.txt"
    assert main(["eval", "--classes", "sscbench-kitti360", "--dataset-root", str(root), "--predictions",
                 str(tmp_path / "preds"), "--split", "valid", "--out", str(out)]) == 0
    scores = yaml.safe_load(out.read_text())
    want = _naive_scores(truths, preds)
    assert scores["iou_completion"] == pytest.approx(want["iou"], rel=1e-12)
    assert scores["precision_completion"] == pytest.approx(want["precision"], rel=1e-9)
    assert scores["recall_completion"] == pytest.approx(want["recall"], rel=1e-9)
    assert scores["iou_mean"] == pytest.approx(want["miou"], rel=1e-9)
    from distilkit.data.sscbench import NAMES

    assert [scores[f"iou_{n}"] for n in NAMES[1:]] == pytest.approx(want["class_iou"], rel=1e-9)
    assert scores["iou_motorcycle"] == 0.0 and 0.0 < scores["iou_mean"] < 1.0
    box = np.zeros(SHAPE, bool)
    box[:128, 64:192] = True  # VoxFormer's 25.6 m box: x in [0, 25.6), y in [-12.8, 12.8)
    assert scores["iou_mean_25.6m"] == pytest.approx(_naive_scores(truths, preds, box)["miou"], rel=1e-9)


def test_eval_names_a_missing_prediction(folder, tmp_path, capsys) -> None:
    root, frames = folder
    write_prediction(tmp_path / "preds", VALID, "000000", frames[(VALID, "000000")].truth)
    assert main(["eval", "--classes", "sscbench-kitti360", "--dataset-root", str(root), "--predictions",
                 str(tmp_path / "preds"), "--sequences", "06"]) != 0
    assert "000005_1_1.npy: no prediction for this frame" in _said(capsys)


@pytest.mark.parametrize("calibrated", [False, True])
def test_the_camera_reads_the_image_and_its_calibration(tmp_path, calibrated) -> None:
    from distilkit.data.sscbench_camera import MONOSCENE_CAM_TO_VELO, MONOSCENE_P

    root = tmp_path / "KITTI-360"
    frames = write_folder(root, {6: ("000000",)}, calibration=calibrated)
    ds = SscbenchDataset(SscbenchParams(root=str(root), train=["06"], val=None, camera={}), "train")
    s = ds[0]
    from PIL import Image

    written = np.asarray(Image.open(root / "data_2d_raw" / VALID / "image_00" / "data_rect" / "000000.png"))
    assert s["image"].shape == (1, 376, 1408, 3) and np.array_equal(s["image"][0], written)
    p, c2v = (P_RECT, CAM_TO_VELO) if calibrated else (MONOSCENE_P, MONOSCENE_CAM_TO_VELO)
    t = np.linalg.inv(np.vstack([c2v, [0, 0, 0, 1]]))
    assert np.allclose(s["intrinsics"][0], p[:, :3], atol=1e-4) and np.allclose(s["lidar_to_camera"][0], t, atol=1e-5)
    # the depth: each pixel's nearest occupied voxel centre along the camera's z, counted point by point
    xyz = s["points"][:, :3].astype(np.float64)
    cam = xyz @ t[:3, :3].T + t[:3, 3]
    nearest: dict[tuple[int, int], float] = {}
    for x, y, z in cam:
        if 1e-3 < z <= 80.0:
            u, v = int(np.floor((p[0, 0] * x + p[0, 2] * z) / z)), int(np.floor((p[1, 1] * y + p[1, 2] * z) / z))
            if 0 <= u < 1408 and 0 <= v < 376:
                nearest[(v, u)] = min(z, nearest.get((v, u), np.inf))
    depth = s["depth"]
    assert len(nearest) > 100 and np.count_nonzero(depth) == len(nearest)
    assert all(abs(depth[k] - z) < 1e-4 for k, z in nearest.items())
    assert frames[(VALID, "000000")].occupied_input.sum() == len(xyz)
    if calibrated:
        rotated = SscbenchDataset(SscbenchParams(root=str(root), train=["06"], val=None,
                                                 camera={"rectify_rotation": True, "height": 94, "width": 352}),
                                  "train")[0]
        rect = np.eye(4)
        rect[:3, :3] = R_RECT
        assert np.allclose(rotated["lidar_to_camera"][0], rect @ t, atol=1e-5)
        assert np.allclose(rotated["intrinsics"][0, 0], [P_RECT[0, 0] / 4, 0, (P_RECT[0, 2] + 0.5) / 4 - 0.5])
        assert rotated["image"].shape == (1, 94, 352, 3)


def test_the_camera_wants_the_image_and_only_the_current_frame(folder, tmp_path) -> None:
    from pydantic import ValidationError

    root, _ = folder
    with pytest.raises(ValidationError, match="only the current image"):
        SscbenchParams(root=str(root), camera={"previous": [3]})
    bare = tmp_path / "bare"
    write_folder(bare, {6: ("000000",)}, images=False)
    problem = sscbench_check(SscbenchParams(root=str(bare), train=["06"], val=None, camera={}), "train")
    assert "image_00/data_rect/000000.png: missing (the camera's image)" in problem
    calibrated = tmp_path / "calibrated"
    write_folder(calibrated, {6: ("000000",)}, calibration=True)
    params = SscbenchParams(root=str(calibrated), train=["06"], val=None, camera={})
    persp = calibrated / "calibration" / "perspective.txt"
    persp.write_text("\n".join(line.rsplit(" ", 1)[0] if line.startswith("P_rect_00") else line
                               for line in persp.read_text().splitlines()))
    assert "perspective.txt: P_rect_00 has 11 numbers, expected 12" in sscbench_check(params, "train")
    (calibrated / "calibration" / "calib_cam_to_velo.txt").unlink()
    assert "calib_cam_to_velo.txt: not found" in sscbench_check(params, "train")


def test_a_recipe_trains_on_the_folder_and_scores_its_test_drive(folder, tmp_path) -> None:
    """As a user runs it: a recipe whose data is the folder trains a stage (2 steps, the grid coarsened 8x) and
    scores the benchmark's test drive with its 19 classes."""
    import json

    import yaml

    from conftest import tiny_recipe
    from distilkit.cli import main

    root, _ = folder
    recipe = tiny_recipe(steps=2, distill=False)
    recipe["stages"].pop("student", None)
    recipe["stages"]["teacher"]["model"]["params"]["frames"] = 1  # the folder has no scans: one voxelised input
    recipe["data"] = {"dataset": "sscbench-kitti360",
                      "params": {"root": str(root), "scale": 8, "train": ["2013_05_28_drive_0000_sync"],
                                 "val": ["2013_05_28_drive_0006_sync"]}}
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["run", str(path), "-o", str(tmp_path / "runs"), "-q"]) == 0
    (summary_path,) = (tmp_path / "runs").glob("*/teacher-*/summary.json")
    summary = json.loads(summary_path.read_text())
    assert summary["status"] == "finished" and summary["steps"] == 2 and summary["report_split"] == "test"
    assert summary["classes"]["names"][:2] == ["empty", "car"] and len(summary["classes"]["names"]) == 19
    assert len(summary["test"]["best"]["class_iou"]) == 18 and 0.0 < summary["test"]["best"]["iou"] <= 1.0
