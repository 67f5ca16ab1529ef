"""End to end: the README's quickstart through the CLI, then again (every stage reused)."""

from __future__ import annotations

import subprocess
import sys

import pytest
import yaml

from conftest import ROOT


@pytest.mark.slow
def test_quickstart_runs_and_reuses(tmp_path) -> None:
    cmd = [sys.executable, "-m", "distilkit", "run", str(ROOT / "recipes" / "quickstart.yaml"), "-o", str(tmp_path)]
    first = subprocess.run(cmd, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "student + DSKD" in first.stdout and "mIoU" in first.stdout and "test split" in first.stdout
    second = subprocess.run(cmd, capture_output=True, text=True)
    assert second.returncode == 0 and second.stdout.count("reused from") == 4  # nothing trained again
    assert (tmp_path / "quickstart" / "report.md").is_file()


@pytest.mark.slow
def test_cross_adapter_recipe_runs_both_ways(tmp_path) -> None:
    """The shipped recipe: SCPNet -> JS3C-Net and JS3C-Net -> SCPNet, DSKD across grids, to the end."""
    import json

    cmd = [sys.executable, "-m", "distilkit", "run", str(ROOT / "recipes" / "cross_adapters.yaml"), "-o", str(tmp_path),
           "-q"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    summaries = [json.loads(p.read_text()) for p in (tmp_path / "cross_adapters").glob("*/summary.json")]
    assert sorted(s["stage"] for s in summaries) == ["js3cnet_from_scpnet", "js3cnet_teacher", "scpnet_from_js3cnet",
                                                    "scpnet_teacher"]
    assert all(s["status"] == "finished" and 0 <= s["test"]["best"]["miou"] <= 1 for s in summaries)


@pytest.mark.slow
def test_scorelidar_recipe_prints_the_table_4_comparison(tmp_path) -> None:
    """LiDiff teacher, ScoreLiDAR and Distillation-DPO students, each at 8 / 4 / 2 / 1 steps, the teacher also at 50
    steps, without guidance and refined; each with its seconds per scene (the speed-ups themselves are measured side
    by side by `distilkit bench sampler guidance`, not asserted on a busy machine)."""
    import json

    cmd = [sys.executable, "-m", "distilkit", "run", str(ROOT / "recipes" / "scorelidar.yaml"), "-o", str(tmp_path)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "CD best" in done.stdout and "JSD best" in done.stdout
    summaries = {s["stage"]: s for s in (json.loads(p.read_text()) for p in
                                         (tmp_path / "scorelidar").glob("*/summary.json"))}
    stages = yaml.safe_load((ROOT / "recipes" / "scorelidar.yaml").read_text())["stages"]
    steps = {"_8" if n == 8 else f"_{n}" for n in (8, 4, 2, 1)}
    assert set(summaries) == set(stages)  # every row of the recipe ran
    assert {f"teacher{s}" for s in steps} | {f"student{s}" for s in steps - {"_8"}} | {"dpo", "dpo_bounded",
                                                                                      "refined_student"} <= set(stages)
    assert all("emd.emd" in s["test"]["best"] for s in summaries.values())  # Distillation-DPO's metric on every row
    assert summaries["refined_8"]["input"] == "6x refinement" and summaries["student_1"]["input"] == "1 step"
    assert all(s["test"]["best"]["seconds_per_sample"] > 0 for s in summaries.values())
    assert all(s["test"]["best"]["cd"] > 0 and 0 < s["test"]["best"]["jsd"] < 1 for s in summaries.values())
