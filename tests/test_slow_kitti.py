"""End to end on an exported SemanticKITTI folder at full resolution: `distilkit eval` of `distilkit predict`'s
output gives the in-training evaluation's numbers (slow: SCPNet at 256 x 256 x 32 on the CPU)."""

from __future__ import annotations

import pytest
import yaml

from distilkit.cli import main


@pytest.mark.slow
def test_eval_of_predict_equals_the_in_training_evaluation(tmp_path) -> None:
    from distilkit.engine.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    root = tmp_path / "kitti"
    assert main(["data", "export-kitti", str(root), "--frames", "11", "--set", "beams=16", "azimuth_steps=256",
                 "gt_frames=5", "seed=3"]) == 0
    params = {"channels": 4, "point_mlp": [8], "seg_channels": 4, "frames": 1}
    recipe = {"schema_version": 1, "name": "kitti", "seed": 0,
              "data": {"dataset": "semantickitti", "params": {"root": str(root), "train": ["00"],
                                                              "val": ["08"], "scale": 1}},
              "stages": {"scpnet": {"model": {"adapter": "scpnet", "params": params},
                                    "train": {"steps": 1, "batch_size": 1, "eval_every": 1}}}}
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
