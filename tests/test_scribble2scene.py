"""The Scribble2Scene pipeline and the cross-modal recipe end to end: the shipped recipes in miniature by default
(every edge: Dean labels, frozen query proposals, the Teacher-Labeler as teacher, RGO²D with image features), and
``recipes/scribble2scene.yaml`` at its default scale, on a short schedule, in the slow run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from _miniature import shrink
from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT
from distilkit.cli import main
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict

TINY = {"scale": 8, "num_train": 2, "num_val": 1, "num_test": 1, "input_frames": 1, "gt_frames": 3, "beams": 16,
        "azimuth_steps": 256}


def shipped(name: str, steps: int = 2, device: object = "cpu", **camera: object) -> dict:
    """A shipped recipe with every stage at ``steps`` steps (batch 2) on a tiny copy of its data, training on
    ``device`` (the CPU unless a test of the computation passes the ``device`` fixture; not the recipe's auto)."""
    recipe = yaml.safe_load((ROOT / "recipes" / f"{name}.yaml").read_text())
    data = recipe["data"]["params"]
    recipe["data"]["params"] = {**TINY, "input_frames": data.get("input_frames", 1),
                                "camera": {**data.get("camera", {}), "height": 24, "width": 80, **camera}}
    for stage in recipe["stages"].values():
        stage["train"].update(steps=steps, batch_size=2, eval_every=steps, device=str(device))
    return recipe


def summaries(root: Path) -> dict[str, dict]:
    return {p.parent.name.rsplit("-", 1)[0]: json.loads(p.read_text()) for p in root.glob("*/*/summary.json")}


def test_the_scribble2scene_pipeline_runs_every_edge(tmp_path: Path, capsys) -> None:
    recipe = shipped("scribble2scene", steps=1)  # an edge is crossed at the first step
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path, quiet=True)
    assert pipe.resolved.order.index("student") > max(pipe.resolved.order.index(s)
                                                      for s in ("proposal", "dean", "teacher_labeler"))
    results = {r.name: r for r in pipe.run()}
    assert set(results) == {"proposal", "dean", "teacher_labeler", "scribble_baseline", "student"}
    # the Dean-Labeler published its predictions of the training split for the student's labels
    assert (results["dean"].run_dir / "predictions" / "train").is_dir()
    done = summaries(tmp_path)
    assert done["dean"]["test"]["best"]["iou"] == pytest.approx(1.0)  # it keeps the complete geometry
    for name in ("teacher_labeler", "student"):
        assert {"miou_12_8m", "iou_25_6m"} <= set(done[name]["test"]["best"])
    report = (tmp_path / "scribble2scene" / "report.md").read_text()
    assert "IoU per class" in report and "| Teacher-Labeler |" in report and "mIoU 12.8 m" in report


def test_the_cross_modal_recipe_validates_and_a_camera_tap_across_frames_is_refused(tmp_path: Path, capsys) -> None:
    path = tmp_path / "cross.yaml"
    recipe = shipped("cross_modal", previous=[3])
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(path), "--no-memory"]) == 0
    # a student reading one image against a teacher reading two: not one camera's features
    bad = yaml.safe_load(path.read_text())
    bad["stages"]["camera_teacher"]["model"]["params"]["frames"] = 2
    bad["stages"]["camera_from_camera"] = {
        "model": {"adapter": "voxformer"}, "aux": {"proposal": {"from": "proposal"}},
        "teacher": {"from": "camera_teacher"}, "train": {"steps": 1},
        "distill": [{"name": "fitnets", "taps": {"student": "image_features", "teacher": "image_features"}}]}
    with pytest.raises(RecipeError) as err:
        Pipeline(recipe_from_dict(bad), tmp_path / "x", quiet=True)
    assert "stages.camera_from_camera.distill[0]" in str(err.value) and "frame 0" in str(err.value) \
        and "frames 0, -3" in str(err.value)


def test_the_cross_modal_pairs_train(tmp_path: Path, device) -> None:
    recipe = shipped("cross_modal", steps=1, device=device)
    keep = ("lidar_teacher", "camera_teacher", "proposal", "camera_dskd", "camera_rgo2d", "lidar_from_camera")
    recipe["stages"] = {k: v for k, v in recipe["stages"].items() if k in keep}
    results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path, quiet=True).run()}
    assert set(results) == set(keep)
    logged = (results["camera_dskd"].run_dir / "metrics.jsonl").read_text()
    assert '"kd_dskd"' in logged  # the cross-grid relational term was computed and logged


@pytest.mark.slow
def test_the_shipped_scribble2scene_recipe_at_its_default_scale(tmp_path: Path) -> None:
    """`distilkit run recipes/scribble2scene.yaml` at its default scale (its 64 x 64 x 8 grid, five 48 x 160 images,
    its models and losses), each training stage 20 steps on 8 training scenes, scored on 4 (the full schedule, about
    7 minutes on a 2-core CPU with its data, is the README's): the Teacher-Labeler, which proposes the true geometry,
    beats the camera-only student on IoU (0.56 against 0.26 here); the Dean-Labeler keeps the complete geometry."""
    recipe = ROOT / "recipes" / "scribble2scene.yaml"
    assert main(["run", str(recipe), "-o", str(tmp_path), "-q", "--set",
                 *shrink(recipe, 20, num_train=8, num_val=2, num_test=4)]) == 0
    done = summaries(tmp_path)
    teacher, student = done["teacher_labeler"]["test"]["best"], done["student"]["test"]["best"]
    assert teacher["iou"] > student["iou"]
    assert done["dean"]["test"]["best"]["iou"] == pytest.approx(1.0)
    assert all(k in student for k in ("miou_12_8m", "iou_12_8m", "miou_25_6m", "iou_25_6m"))
