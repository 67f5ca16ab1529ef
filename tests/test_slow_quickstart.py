"""End to end: the README's quickstart through the CLI, then again (every stage reused)."""

from __future__ import annotations

import subprocess
import sys

import pytest

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
    """LiDiff teacher, ScoreLiDAR student, evaluated at 50 / 8 / 4 / 2 / 1 steps, each with its seconds per scene
    (the speed-up itself is measured side by side by `distilkit bench sampler`, not asserted on a busy machine)."""
    import json

    cmd = [sys.executable, "-m", "distilkit", "run", str(ROOT / "recipes" / "scorelidar.yaml"), "-o", str(tmp_path)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "CD best" in done.stdout and "JSD best" in done.stdout
    summaries = {s["stage"]: s for s in (json.loads(p.read_text()) for p in
                                         (tmp_path / "scorelidar").glob("*/summary.json"))}
    assert set(summaries) == {"teacher", "teacher_8", "student", "student_4", "student_2", "student_1"}
    assert all(s["test"]["best"]["seconds_per_sample"] > 0 for s in summaries.values())
    assert all(s["test"]["best"]["cd"] > 0 and 0 < s["test"]["best"]["jsd"] < 1 for s in summaries.values())
