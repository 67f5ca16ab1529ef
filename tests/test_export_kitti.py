"""`distilkit data export-kitti`: synthetic streets as a SemanticKITTI folder, read back by the real-data path."""

from __future__ import annotations

import numpy as np
import pytest

from _camera_kitti import camera_kitti
from conftest import folder_recipe
from distilkit.cli import main
from distilkit.data import semantickitti as sk


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """This process's exported folder (tests/_camera_kitti.py: conftest's export_kitti with camera images, which
    adds image_2/ and the intrinsics in calib.txt; scans, labels, voxels and poses are those of a plain export),
    read only: a test that writes into it works on a copy."""
    return camera_kitti(tmp_path_factory)


@pytest.fixture
def no_report(monkeypatch) -> None:
    """The test's runs write no run report (report.md and its figures), which it does not read (tests/test_reports.py
    tests them): a tiny stage's report is about a third of its CPU."""
    import distilkit.report.run

    monkeypatch.setattr(distilkit.report.run, "write_run_report", lambda run_dir: None)


def test_the_folder_has_semantickittis_layout_and_reads_back(exported) -> None:
    seq = exported / "sequences" / "08"
    assert sorted(f.name for f in (seq / "voxels").iterdir()) == [f"{t:06d}.{e}" for t in (0, 5, 10)
                                                                 for e in ("bin", "invalid", "label", "occluded")]
    assert len(list((seq / "velodyne").glob("*.bin"))) == 11 == len(list((seq / "labels").glob("*.label")))
    pts = sk.read_points(seq / "velodyne" / "000003.bin")
    sem, inst = sk.read_point_labels(seq / "labels" / "000003.label", len(pts))
    assert pts.shape[1] == 4 and (np.linalg.norm(pts[:, :3], axis=1) < 60.5).all()  # the sensor frame
    assert set(np.unique(sem)) <= set(range(260)) and (inst[sem >= 252] > 0).all()  # moving objects: instances
    poses = sk.read_poses(seq / "poses.txt", sk.read_calib(seq / "calib.txt"))
    assert poses.shape == (11, 4, 4) and np.allclose(poses[:, :3, :3], np.eye(3), atol=1e-9)
    assert np.allclose(poses[:, :3, 3], [[j * 1.0, 0, 0] for j in range(11)], atol=1e-6)  # 1 m a frame along x
    raw = sk.read_voxel_labels(seq / "voxels" / "000005.label")
    assert raw.shape == (256, 256, 32) and raw.dtype == np.uint16 and raw.any()
    inv = sk.read_voxel_bits(seq / "voxels" / "000005.invalid")
    packed = np.fromfile(seq / "voxels" / "000005.invalid", np.uint8)
    assert np.array_equal(np.unpackbits(packed).astype(bool).reshape(256, 256, 32), inv)  # np.packbits' order
    assert not (inv & (raw > 0)).any()  # an occupied voxel is never invalid


def test_the_dataset_fuses_exported_scans_through_the_poses(exported) -> None:
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticKittiParams

    params = SemanticKittiParams(root=str(exported), train=["00"], val=["08"], input_frames=2,
                                 scale=4)
    ds = SemanticKittiDataset(params, "val")
    assert len(ds) == 3 and ds.sample_id(1) == "08/000005"
    s = ds[1]
    scan6 = sk.read_points(exported / "sequences" / "08" / "velodyne" / "000006.bin")
    assert np.allclose(s["points"][s["point_frame"] == 1][:, :3], scan6[:, :3] + [1.0, 0.0, 0.0], atol=1e-4)
    assert s["voxel_label"].shape == (64, 64, 8) and (s["voxel_label"] != 0).any()


def test_moving_objects_leave_traces_that_rectification_removes(exported, tmp_path, capsys) -> None:
    import shutil

    from distilkit.data.rectify import rectify_folder

    root = tmp_path / "kitti"  # rectify writes voxels_rectified/ beside voxels/: on a copy of the shared folder
    for seq in ("00", "08"):
        shutil.copytree(exported / "sequences" / seq, root / "sequences" / seq,
                        ignore=shutil.ignore_patterns("image_2"))
    counts = rectify_folder(root, ["00", "08"])
    before = sum(b for b, _ in counts.values())
    left = sum(a for _, a in counts.values())
    assert before > 0 and left < before
    static = sk.read_voxel_labels(root / "sequences" / "08" / "voxels" / "000000.label")
    fixed = sk.read_voxel_labels(root / "sequences" / "08" / "voxels_rectified" / "000000.label")
    from distilkit.data.classes import remap, ssc_lut

    dyn = np.isin(remap(static, ssc_lut()), [1, 4, 5, 6, 7, 8])
    assert np.array_equal(fixed[~dyn], static[~dyn])


def test_bad_export_arguments_are_named(tmp_path, capsys) -> None:
    assert main(["data", "export-kitti", str(tmp_path), "--sequences", "eight"]) == 2
    assert "sequence names are numbers" in capsys.readouterr().err
    assert main(["data", "export-kitti", str(tmp_path), "--set", "beams=1"]) == 2
    assert "beams" in capsys.readouterr().err


def test_a_recipe_trains_on_the_folder_publishes_a_hidden_split_and_predict_and_eval_read_it(exported, tmp_path,
                                                                                            capsys, no_report) -> None:
    """One 2-frame SCPNet run (a step) on the exported folder (rectification on) with a hidden test sequence 11
    (scans only, no label files: the benchmark's test split): scores come from the validation split (and the summary
    says so), the hidden frames' predictions are published; then `distilkit predict` writes the validation sequence
    and the hidden one in the submission format, upsampled from scale 4 to 256 x 256 x 32, and `distilkit eval`
    scores the validation one."""
    import shutil

    from distilkit.data.classes import LEARNING_MAP_INV
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.engine.infer.predict import upsample
    from distilkit.recipe import recipe_from_dict

    root = tmp_path / "kitti"
    for seq in ("00", "08"):
        shutil.copytree(exported / "sequences" / seq, root / "sequences" / seq)
    hidden = root / "sequences" / "11"
    shutil.copytree(root / "sequences" / "08", hidden, ignore=shutil.ignore_patterns("*.label"))
    recipe = folder_recipe(root, "hidden", frames=2, steps=1, publish=["test"], train=["00"], val=["08"],
                           test=["11"], scale=4, input_frames=2, rectify=True)
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    scores = result.summary["test"]["best"]  # the scores block; report_split says which split it holds
    assert result.summary["report_split"] == "val" and 0 <= scores["miou"] <= 1 and 0 <= scores["iou"] <= 1
    assert len(list((result.run_dir / "predictions" / "test").glob("*"))) > 0
    out = tmp_path / "preds"
    assert main(["predict", str(result.run_dir), "--dataset-root", str(root), "--sequences", "08", "11",
                 "--out", str(out)]) == 0
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.label"))
    assert files == [f"sequences/{s}/predictions/{t:06d}.label" for s in ("08", "11") for t in (0, 5, 10)]
    raw = np.fromfile(out / "sequences" / "11" / "predictions" / "000005.label", "<u2")
    assert raw.size == 256 * 256 * 32 and set(np.unique(raw)) <= set(LEARNING_MAP_INV.values())
    blocks = raw.reshape(64, 4, 64, 4, 8, 4)
    assert (blocks == blocks[:, :1, :, :1, :, :1]).all()  # upsampled: constant over each 4 x 4 x 4 block
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(out), "--sequences", "08"]) == 0
    assert "3 frames" in capsys.readouterr().out
    small = np.arange(8).reshape(2, 2, 2)
    assert upsample(small, 2)[3, 2, 1] == small[1, 1, 0] and upsample(small, 2).shape == (4, 4, 4)


def test_roles_take_an_official_split_or_sequences_and_older_names_still_read() -> None:
    from pydantic import ValidationError

    from distilkit.data.params import KITTI_SPLITS, SemanticKittiParams, SemanticPossParams

    default = SemanticKittiParams(root="r")
    assert default.sequences("train") == list(KITTI_SPLITS["train"]) and default.sequences("val") == ["08"]
    assert default.sequences("test") == []  # the hidden test split is predicted, not scored, unless asked for
    assert SemanticKittiParams(root="r", test="test").sequences("test") == [f"{s}" for s in range(11, 22)]
    assert SemanticPossParams(root="r").sequences("val") == ["02"] and SemanticPossParams(root="r", val="test").sequences("val") == ["02"]
    older = SemanticKittiParams(root="r", train_sequences=["00"], val_sequences=[], test_sequences=["08"])
    assert (older.train, older.val, older.test) == (["00"], None, ["08"])
    for bad, said in (({"val": [8]}, "string"), ({"val": "validation"}, "valid"), ({"train": None}, "train"),
                      ({"val": ["8a"]}, "digit strings"), ({"val": ["08"], "val_sequences": ["08"]}, "older name")):
        with pytest.raises(ValidationError, match=said):
            SemanticKittiParams(root="r", **bad)


def test_a_stage_trains_without_a_validation_split(exported, tmp_path) -> None:
    """val: none -> no evaluation during training, the last checkpoint is the model; with no test split either,
    nothing is scored (a stage trained on everything for a submission) and predictions are still published. Every
    10th scan (the voxel frames 0 and 10 of each sequence): what is published and scored, not how much."""
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    def recipe(test):
        return folder_recipe(exported, "noval", "semantickitti-ssc", steps=2, eval_every=1, publish=["train"],
                             train=["00", "08"], val=None, test=test, scale=4, stride=10)

    (alone,) = Pipeline(recipe_from_dict(recipe(None)), tmp_path / "runs", quiet=True).run()
    assert alone.summary["report_split"] is None and alone.summary["test"] == {} and alone.summary["last"] is None
    assert (alone.run_dir / "checkpoints" / "last.pt").is_file() and not (alone.run_dir / "checkpoints" / "best.pt").exists()
    assert not (alone.run_dir / "preview.npz").exists() and (alone.run_dir / "report.md").is_file()
    assert len(list((alone.run_dir / "predictions" / "train").glob("*"))) > 0
    assert not any('"eval"' in line for line in (alone.run_dir / "metrics.jsonl").read_text().splitlines())
    (tested,) = Pipeline(recipe_from_dict(recipe(["08"])), tmp_path / "runs", quiet=True).run()
    assert tested.summary["report_split"] == "test" and tested.summary["test"]["best_step"] == 2
    assert tested.summary["test"]["best"] == tested.summary["test"]["last"]  # no validation: best is the last


def test_the_scan_dataset_gives_every_scan_with_its_point_labels(exported, tmp_path) -> None:
    """semantickitti-scan: 11 scans a sequence, each fused with the next through the poses, point labels from
    labels/, voxel targets on the every-5th frames and ignored on the others; a missing label file is named."""
    import shutil

    from distilkit.data.classes import IGNORE_INDEX, remap, seg_lut
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.params import SemanticKittiScanParams
    from distilkit.errors import DataError
    from distilkit.registry import DATASETS

    params = DATASETS.entry("semantickitti-scan").meta["params"](root=str(exported), train=["00"], val=["08"],
                                                                   input_frames=2, scale=4)
    assert isinstance(params, SemanticKittiScanParams) and params.stride == 1
    ds = SemanticKittiDataset(params, "val")
    assert len(ds) == 11 and [ds.sample_id(i) for i in (0, 3, 10)] == ["08/000000", "08/000003", "08/000010"]
    seq = exported / "sequences" / "08"
    s3, s5 = ds[3], ds[5]
    scan4 = sk.read_points(seq / "velodyne" / "000004.bin")
    assert np.allclose(s3["points"][s3["point_frame"] == 1][:, :3], scan4[:, :3] + [1.0, 0.0, 0.0], atol=1e-4)
    sem, _ = sk.read_point_labels(seq / "labels" / "000003.label")
    assert np.array_equal(s3["point_label"][s3["point_frame"] == 0], remap(sem, seg_lut()))
    assert (s3["voxel_label"] == IGNORE_INDEX).all() and s3["invalid"].all()  # no voxel file for frame 3
    assert (s5["voxel_label"] != IGNORE_INDEX).any()
    root = tmp_path / "k"
    shutil.copytree(seq, root / "sequences" / "08")
    (root / "sequences" / "08" / "labels" / "000007.label").unlink()
    with pytest.raises(DataError, match=r"sequences/08/labels/000007.label: missing \(the scan's point labels\)"):
        SemanticKittiDataset(SemanticKittiScanParams(root=str(root), train=["08"]), "train")


def test_a_multi_frame_teacher_trains_on_every_scan_and_predicts_the_benchmark_frames(exported, tmp_path,
                                                                                       no_report) -> None:
    """Scored on sequence 08 as a test split (no validation split: its 11 scans are evaluated once after training,
    not at a validation step and again at the best and the last checkpoint)."""
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    recipe = folder_recipe(exported, "scans", "semantickitti-scan", frames=2, steps=2, batch_size=2, stage="teacher",
                           train=["00"], val=None, test=["08"], scale=4, input_frames=2)
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert 0 <= result.summary["test"]["best"]["miou"] <= 1
    out = tmp_path / "preds"
    assert main(["predict", str(result.run_dir), "--dataset-root", str(exported), "--sequences", "08",
                 "--out", str(out)]) == 0
    assert sorted(p.name for p in (out / "sequences" / "08" / "predictions").iterdir()) == [
        f"{t:06d}.label" for t in (0, 5, 10)]


def test_point_labels_and_calibration_round_trip(tmp_path) -> None:
    from distilkit.data.export import lidar_to_camera, write_calib

    rng = np.random.default_rng(4)
    sem, inst = rng.integers(0, 1 << 16, 500), rng.integers(0, 1 << 16, 500)
    sk.write_point_labels(tmp_path / "a.label", sem, inst)
    got_sem, got_inst = sk.read_point_labels(tmp_path / "a.label", 500)
    assert np.array_equal(got_sem, sem) and np.array_equal(got_inst, inst)
    k = np.array([[92.5, 0.0, 78.25], [0.0, 91.75, 23.5], [0.0, 0.0, 1.0]])
    write_calib(tmp_path / "calib.txt", lidar_to_camera(), k)
    calib = sk.read_calib(tmp_path / "calib.txt")
    assert np.allclose(calib["P2"][:3, :3], k, rtol=1e-9) and np.allclose(calib["Tr"], lidar_to_camera(), atol=1e-9)


def test_class_weighted_losses_follow_semanticposs_twelve_classes(exported, tmp_path, device, no_report) -> None:
    """JS3C-Net's weighted uncertainty loss and VoxFormer's weighted CE size their class weights by the data's class
    table (they were SemanticKITTI's 20 whatever the data): both train on a semanticposs-ssc folder (12 classes),
    scored on a test split (no validation split: one evaluation a stage instead of three)."""
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    small = {"seg_channels": 4, "embed": 4, "ssc_channels": 4, "pvi_hidden": 4}
    recipe = {"schema_version": 1, "name": "poss", "seed": 0,
              "data": {"dataset": "semanticposs-ssc",
                       "params": {"root": str(exported), "train": ["00"], "val": None, "test": ["08"],
                                  "scale": 4}},
              "stages": {"js3cnet": {"model": {"adapter": "js3cnet", "params": small},
                                     "train": {"steps": 1, "batch_size": 1, "eval_every": 1, "device": device.type}},
                         "weighted": {"model": {"adapter": "scpnet", "params": {"channels": 4, "point_mlp": [8],
                                                                              "seg_channels": 4}},
                                      "task_losses": [{"name": "weighted_ce"}, {"name": "geo_scal"},
                                                      {"name": "sem_scal"}],
                                      "train": {"steps": 1, "batch_size": 1, "eval_every": 1,
                                                "device": device.type}}}}
    results = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    for result in results:
        assert len(result.summary["classes"]["names"]) == 12 and 0 <= result.summary["test"]["best"]["miou"] <= 1


def test_scribblesc_scribbles_round_trip_through_the_folder_dataset(exported) -> None:
    """export-kitti writes ScribbleSC's layout (scribblesc/sequences/NN/voxels/*.label: raw ids of scribbled voxels,
    0 elsewhere); semantickitti-ssc reads it as `scribble` (classes, 254 occupied-unscribbled, 0 empty, 255 invalid)."""
    from distilkit.data.classes import IGNORE_INDEX, SCRIBBLE_UNLABELLED, remap, ssc_lut
    from distilkit.registry import DATASETS

    path = exported / "scribblesc" / "sequences" / "08" / "voxels" / "000005.label"
    raw = sk.read_voxel_labels(path)
    dense_raw = sk.read_voxel_labels(exported / "sequences" / "08" / "voxels" / "000005.label")
    assert raw.dtype == np.uint16 and 0 < (raw > 0).sum() < (dense_raw > 0).sum() and not (raw[dense_raw == 0]).any()
    entry = DATASETS.entry("semantickitti")
    ds = entry.obj(entry.meta["params"](root=str(exported), train=["08"], val=None, scribbles="scribblesc"), "train")
    sample = ds[[ds.sample_id(i) for i in range(len(ds))].index("08/000005")]
    dense = remap(dense_raw, ssc_lut())
    inv = sk.read_voxel_bits(exported / "sequences" / "08" / "voxels" / "000005.invalid")
    want = np.where((dense != 0) & (dense != IGNORE_INDEX), SCRIBBLE_UNLABELLED, 0)
    want = np.where(raw != 0, remap(raw, ssc_lut()), want)
    want = np.where(inv, IGNORE_INDEX, want)
    assert np.array_equal(sample["scribble"], want)
    labelled = (want != 0) & (want != SCRIBBLE_UNLABELLED) & (want != IGNORE_INDEX)
    assert labelled.any() and (want == SCRIBBLE_UNLABELLED).any()
    assert "scribble" in entry.meta["info"](ds.p).fields
    coarse = entry.obj(entry.meta["params"](root=str(exported), train=["08"], val=None, scribbles="scribblesc",
                                            scale=4), "train")[0]["scribble"]
    assert coarse.shape == (64, 64, 8) and ((coarse > 0) & (coarse < 20)).any()


def test_a_term_that_needs_scribbles_is_refused_without_them(exported, tmp_path, capsys) -> None:
    """RGO²D's class centres never fall back to the dense labels: validate names the missing scribbles (exit 2)."""
    import yaml

    recipe = folder_recipe(exported, train=["00"], val=["08"], scale=4)
    recipe["stages"]["student"] = {**recipe["stages"]["scpnet"], "teacher": {"from": "scpnet"},
                                   "distill": [{"name": "rgo2d"}]}
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(path), "--no-memory"]) == 2
    err = capsys.readouterr()
    assert "'scribble'" in err.err + err.out and "scribbles: FOLDER" in err.err + err.out
    recipe["data"]["params"]["scribbles"] = "scribblesc"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(path), "--no-memory"]) == 0
    recipe["data"]["params"].pop("scribbles")
    recipe["stages"]["student"]["distill"] = [{"name": "rgo2d", "taps": {"labels": "voxel_target"}}]
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(path), "--no-memory"]) == 0  # the dense labels, when asked for by name
