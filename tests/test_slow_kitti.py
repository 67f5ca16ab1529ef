"""End to end on an exported SemanticKITTI folder at full resolution: `distilkit eval` of `distilkit predict`'s
output gives the in-training evaluation's numbers (slow: SCPNet at 256 x 256 x 32 on the CPU), and the shipped
SemanticKITTI recipe runs on such a folder. Both read one exported folder (nothing writes into it)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from conftest import export_kitti, folder_recipe
from distilkit.cli import main

pytestmark = pytest.mark.xdist_group("slow_kitti")  # one worker exports the folder for both


@pytest.fixture(scope="module")
def kitti(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two 11-scan sequences (00, 08) exported from the synthetic streets (conftest's EXPORT_SET: 16 beams)."""
    return export_kitti(tmp_path_factory.mktemp("slow_kitti") / "kitti")


@pytest.mark.slow
def test_eval_of_predict_equals_the_in_training_evaluation(kitti, tmp_path) -> None:
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    root = kitti
    recipe = folder_recipe(root, train=["00"], val=["08"], scale=1)
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert result.summary["report_split"] == "val"
    trained = result.summary["test"]["best"]
    out = tmp_path / "preds"
    assert main(["predict", str(result.run_dir), "--dataset-root", str(root), "--split", "valid", "--out", str(out)]) == 0
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(out), "--split", "valid"]) == 0
    got = yaml.safe_load((out / "scores.txt").read_text())
    assert got["iou_mean"] == pytest.approx(trained["miou"], abs=1e-12)
    assert got["iou_completion"] == pytest.approx(trained["iou"], abs=1e-12)
    assert got["precision_completion"] == pytest.approx(trained["precision"], abs=1e-12)
    assert got["recall_completion"] == pytest.approx(trained["recall"], abs=1e-12)
    assert got["iou_mean_25.6m"] == pytest.approx(trained["miou_25_6m"], abs=1e-12)
    assert got["iou_completion_12.8m"] == pytest.approx(trained["iou_12_8m"], abs=1e-12)


@pytest.mark.slow
def test_the_shipped_kitti_recipe_runs_on_an_exported_folder(kitti, tmp_path) -> None:
    """recipes/semantickitti_scpnet.yaml unchanged but for the root, the sequences and smaller sizes: teacher on 5
    fused scans with rectified labels, student with and without DSKD, then predict and eval of the distilled one."""
    root = kitti
    sizes = [f"stages.{s}.{k}" for s in ("teacher", "student", "student_dskd")
             for k in ("model.params.channels=4", "model.params.point_mlp=[8]", "model.params.seg_channels=4",
                       "train.epochs=null", "train.steps=2", "train.batch_size=1")]
    recipe = Path(__file__).resolve().parents[1] / "recipes" / "semantickitti_scpnet.yaml"
    assert main(["run", str(recipe), "-o", str(tmp_path / "runs"), "-q", "--set", f"data.params.root={root}",
                 "data.params.train=['00']", "data.params.val=['08']", "data.params.scale=4", *sizes]) == 0
    (run,) = (tmp_path / "runs" / "semantickitti_scpnet").glob("student_dskd-*")
    summary = yaml.safe_load((run / "summary.json").read_text())
    assert summary["objectives"] == ["dskd×3000"] and summary["input"] == "1 frame"
    assert main(["predict", str(run), "--dataset-root", str(root), "--split", "valid", "--out",
                 str(tmp_path / "preds")]) == 0
    assert main(["eval", "--dataset-root", str(root), "--predictions", str(tmp_path / "preds"), "--split", "valid"]) == 0
    scores = yaml.safe_load((tmp_path / "preds" / "scores.txt").read_text())
    assert 0 <= scores["iou_mean"] <= 1 and 0 <= scores["iou_completion"] <= 1
