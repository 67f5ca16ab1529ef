"""``distilkit eval`` and ``predict`` on SSCBench-KITTI-360 (issue 57, items 6, 9 and 14): predictions that are not
class ids refused with the file named, one format a frame, ``predict`` writing what ``eval`` reads, ``eval`` reading
only what scoring needs, and every error said before a progress bar starts."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from _sscbench import DRIVE, SHAPE, write_folder, write_prediction
from distilkit.cli import main

VALID, TEST = DRIVE.format(6), DRIVE.format(9)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("sscbench") / "KITTI-360"
    return root, write_folder(root, images=False)


def _said(capsys) -> str:
    said = capsys.readouterr()
    return " ".join((said.out + said.err).split())


def _eval(root, preds, *extra) -> int:
    return main(["eval", "--classes", "sscbench-kitti360", "--dataset-root", str(root), "--predictions", str(preds),
                 "--sequences", "06", *extra])


def _truths(tmp_path, frames, **kw):
    preds = tmp_path / "preds"
    for frame in ("000000", "000005"):
        write_prediction(preds, VALID, frame, frames[(VALID, frame)].truth % 255, **kw)  # ignored voxels as empty
    return preds


@pytest.mark.parametrize("bad, words", [
    (np.ones(SHAPE, bool), "000005_1_1.npy: a bool array"),
    (np.full(SHAPE, 19, np.uint8), "000005_1_1.npy: 2097152 values are not train ids 0..18"),
    (np.full(SHAPE, 255, np.uint8), "000005_1_1.npy: "),  # 255 where a voxel is scored
    (np.full(SHAPE, 2.5, np.float32), "000005_1_1.npy: 2097152 values are not train ids"),
])
def test_eval_refuses_a_prediction_that_is_not_class_ids_naming_the_file(folder, tmp_path, capsys, bad, words) -> None:
    root, frames = folder
    preds = _truths(tmp_path, frames)
    np.save(preds / VALID / "000005_1_1.npy", bad)
    assert _eval(root, preds) == 2
    said = _said(capsys)
    assert words in said and str(preds / VALID / "000005_1_1.npy") in said


def test_eval_refuses_raw_ids_the_learning_map_ignores_naming_the_file(folder, tmp_path, capsys) -> None:
    root, frames = folder
    preds = _truths(tmp_path, frames, raw=True)
    np.full(SHAPE, 7, "<u2").tofile(preds / VALID / "000005.label")  # KITTI-360's road, not a kitti360.yaml id
    assert _eval(root, preds) == 2
    assert f"{preds / VALID / '000005.label'}: " in _said(capsys)


def test_eval_refuses_a_frame_predicted_in_both_formats(folder, tmp_path, capsys) -> None:
    root, frames = folder
    preds = _truths(tmp_path, frames)
    write_prediction(preds, VALID, "000005", frames[(VALID, "000005")].truth % 255, raw=True)
    assert _eval(root, preds) == 2
    said = _said(capsys)
    assert f"{preds / VALID}/000005: both 000005_1_1.npy and 000005.label" in said and "0/?" not in said


def test_eval_names_a_missing_predictions_folder_and_starts_no_bar_before_an_error(folder, tmp_path, capsys) -> None:
    root, frames = folder
    assert _eval(root, tmp_path / "nowhere") == 2
    said = _said(capsys)
    assert f"{tmp_path / 'nowhere'}: no such folder" in said and "no prediction for this frame" not in said
    assert "0/?" not in said and "━" not in said
    (tmp_path / "preds").mkdir()
    assert _eval(root, tmp_path / "preds") == 2
    said = _said(capsys)
    assert f"{tmp_path / 'preds' / VALID}: no such folder" in said and "0/?" not in said
    # SemanticKITTI's evaluation the same
    kitti = tmp_path / "kitti"
    (kitti / "sequences" / "08" / "voxels").mkdir(parents=True)
    np.zeros(SHAPE, "<u2").tofile(kitti / "sequences" / "08" / "voxels" / "000000.label")
    assert main(["eval", "--dataset-root", str(kitti), "--predictions", str(tmp_path / "nowhere")]) == 2
    said = _said(capsys)
    assert "━" not in said and f"{tmp_path / 'nowhere'}: no such folder" in said


def test_eval_reads_no_input_scan_and_takes_preprocess_targets(folder, tmp_path, capsys) -> None:
    root, frames = folder
    preds = _truths(tmp_path, frames)
    pred = np.load(preds / VALID / "000000_1_1.npy")
    pred[:, :128] = 0  # half of it wrong
    np.save(preds / VALID / "000000_1_1.npy", pred)
    assert _eval(root, preds, "--out", str(tmp_path / "a.txt")) == 0
    bare = tmp_path / "KITTI-360"  # the labels alone: no .bin, and for preprocess no .label / .invalid either
    shutil.copytree(root / "data_2d_raw" / VALID, bare / "data_2d_raw" / VALID, ignore=shutil.ignore_patterns("*.bin"))
    shutil.copytree(root / "preprocess" / "labels" / VALID, bare / "preprocess" / "labels" / VALID)
    assert _eval(bare, preds, "--out", str(tmp_path / "b.txt")) == 0
    shutil.rmtree(bare / "data_2d_raw")
    assert _eval(bare, preds, "--targets", "preprocess", "--out", str(tmp_path / "c.txt")) == 0
    a, b, c = (yaml.safe_load((tmp_path / f"{n}.txt").read_text()) for n in "abc")
    assert a == b == c and 0.0 < a["iou_mean"] < 1.0
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(preds), "--targets", "preprocess"]) == 2
    assert "--targets" in _said(capsys)


def test_predict_writes_what_eval_reads_for_a_run_trained_on_the_folder(folder, tmp_path, capsys) -> None:
    import json

    from conftest import tiny_recipe

    root, _ = folder
    recipe = tiny_recipe(steps=2, distill=False)
    recipe["stages"].pop("student", None)
    recipe["stages"]["teacher"]["model"]["params"]["frames"] = 1
    recipe["data"] = {"dataset": "sscbench-kitti360", "params": {"root": str(root), "scale": 8, "train": ["00"],
                                                                 "val": ["06"]}}
    (path := tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    assert main(["run", str(path), "-o", str(tmp_path / "runs"), "-q"]) == 0
    (run,) = (tmp_path / "runs").glob("*/teacher-*")
    capsys.readouterr()
    assert main(["predict", str(run), "--dataset-root", str(root), "--split", "test", "--out",
                 str(tmp_path / "p")]) == 0
    assert f"{tmp_path / 'p'}/<drive>/FFFFFF_1_1.npy" in _said(capsys)
    written = np.load(tmp_path / "p" / TEST / "000010_1_1.npy")
    assert written.dtype == np.uint8 and written.shape == SHAPE and written.max() < 19
    assert (written == np.repeat(np.repeat(np.repeat(written[::8, ::8, ::8], 8, 0), 8, 1), 8, 2)).all()
    assert main(["eval", "--classes", "sscbench-kitti360", "--dataset-root", str(root), "--predictions",
                 str(tmp_path / "p"), "--split", "test"]) == 0
    scores = yaml.safe_load((tmp_path / "p" / "scores.txt").read_text())
    summary = json.loads((run / "summary.json").read_text())
    assert 0.0 <= scores["iou_mean"] <= 1.0 and summary["classes"]["names"][1] == "car"
    capsys.readouterr()  # test-time voting: a group named as in a recipe; the run's own, which it trained without
    assert main(["predict", str(run), "--dataset-root", str(root), "--split", "test", "--out", str(tmp_path / "v"),
                 "--vote", "{flip: [x, y], rotate90: z}"]) == 0
    voted = np.load(tmp_path / "v" / TEST / "000010_1_1.npy")
    assert voted.dtype == np.uint8 and voted.shape == SHAPE and voted.max() < 19
    assert main(["predict", str(run), "--dataset-root", str(root), "--split", "test", "--out", str(tmp_path / "w"),
                 "--vote", "train"]) == 2
    assert "--vote train: the run trained without augmentation" in _said(capsys)
    assert main(["predict", str(run), "--dataset-root", str(root), "--split", "test", "--out", str(tmp_path / "w"),
                 "--vote", "{flip: [z]}"]) == 2
    assert "--vote:" in _said(capsys)
    capsys.readouterr()
    assert main(["predict", str(run), "--dataset-root", str(tmp_path / "missing"), "--split", "test", "--out",
                 str(tmp_path / "q")]) == 2
    said = _said(capsys)
    assert "0/?" not in said and "━" not in said and "missing" in said
