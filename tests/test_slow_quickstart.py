"""End to end: the README's quickstart through the CLI, then again (every stage reused); the cross-adapter and
ScoreLiDAR recipes to the end. Each runs the shipped recipe in miniature (tests/_miniature.py: every training stage a
few steps on a few scenes; the models, grids and sampler step counts the recipe's), in this process."""

from __future__ import annotations

import json

import pytest
import yaml

from _miniature import shrink
from conftest import ROOT
from distilkit.cli import main

QUICKSTART = ROOT / "recipes" / "quickstart.yaml"


@pytest.mark.slow
def test_quickstart_runs_and_reuses(tmp_path, capsys) -> None:
    """The quickstart's table (its labels, mIoU, the test split) and report; run again, all 4 stages are reused."""
    cmd = ["run", str(QUICKSTART), "-o", str(tmp_path), "--set",
           *shrink(QUICKSTART, 2, num_train=2, num_val=2, num_test=2)]
    assert main(cmd) == 0
    first = capsys.readouterr().out
    assert "student + DSKD" in first and "mIoU" in first and "test split" in first
    assert main(cmd) == 0
    assert capsys.readouterr().out.count("reused from") == 4  # nothing trained again
    assert (tmp_path / "quickstart" / "report.md").is_file()


@pytest.mark.slow
def test_cross_adapter_recipe_runs_both_ways(tmp_path) -> None:
    """The shipped recipe: SCPNet -> JS3C-Net and JS3C-Net -> SCPNet, DSKD across grids, to the end."""
    recipe = ROOT / "recipes" / "cross_adapters.yaml"
    assert main(["run", str(recipe), "-o", str(tmp_path), "-q", "--set",
                 *shrink(recipe, 2, num_train=2, num_val=2, num_test=2)]) == 0
    summaries = [json.loads(p.read_text()) for p in (tmp_path / "cross_adapters").glob("*/summary.json")]
    assert sorted(s["stage"] for s in summaries) == ["js3cnet_from_scpnet", "js3cnet_teacher", "scpnet_from_js3cnet",
                                                    "scpnet_teacher"]
    assert all(s["status"] == "finished" and 0 <= s["test"]["best"]["miou"] <= 1 for s in summaries)


@pytest.mark.slow
def test_scorelidar_recipe_prints_the_table_4_comparison(tmp_path, capsys) -> None:
    """LiDiff teacher, ScoreLiDAR and Distillation-DPO students, each at 8 / 4 / 2 / 1 steps, the teacher also at 50
    steps, without guidance and refined; each with its seconds per scene (the speed-ups themselves are measured side
    by side by `distilkit bench sampler guidance`, not asserted on a busy machine). Every row of the recipe at its
    own sampler steps and scan sizes; the stages that train, 2 steps on 2 training scenes, scored on 1 scene."""
    recipe = ROOT / "recipes" / "scorelidar.yaml"
    assert main(["run", str(recipe), "-o", str(tmp_path), "--set",
                 *shrink(recipe, 2, num_train=2, num_val=1, num_test=1)]) == 0
    out = capsys.readouterr().out
    assert "CD best" in out and "JSD best" in out
    summaries = {s["stage"]: s for s in (json.loads(p.read_text()) for p in
                                         (tmp_path / "scorelidar").glob("*/summary.json"))}
    stages = yaml.safe_load(recipe.read_text())["stages"]
    steps = {"_8" if n == 8 else f"_{n}" for n in (8, 4, 2, 1)}
    assert set(summaries) == set(stages)  # every row of the recipe ran
    assert {f"teacher{s}" for s in steps} | {f"student{s}" for s in steps - {"_8"}} | {"dpo", "dpo_bounded",
                                                                                      "refined_student"} <= set(stages)
    assert all("emd.emd" in s["test"]["best"] for s in summaries.values())  # Distillation-DPO's metric on every row
    assert summaries["refined_8"]["input"] == "6x refinement" and summaries["student_1"]["input"] == "1 step"
    assert all(s["test"]["best"]["seconds_per_sample"] > 0 for s in summaries.values())
    assert all(s["test"]["best"]["cd"] > 0 and 0 < s["test"]["best"]["jsd"] < 1 for s in summaries.values())
