"""`distilkit report FOLDER` on what its help offers: a stage run, a recipe's output folder, or a folder of runs
(``runs/``, the ``-o`` a user gave ``distilkit run`` or ``distilkit sweep``), at any depth."""

from __future__ import annotations

import json
from pathlib import Path

from test_compare_classes import fake_run
from distilkit.cli import main
from distilkit.data.classes import CLASS_NAMES


def test_report_of_a_folder_of_runs_rerenders_every_stage_under_it(tmp_path, capsys) -> None:
    iou = {n: 0.1 for n in CLASS_NAMES}
    runs = tmp_path / "runs"
    stages = [fake_run(runs / "quickstart" / "teacher-1a", list(CLASS_NAMES), iou),
              fake_run(runs / "quickstart" / "student-2b", list(CLASS_NAMES), iou),
              fake_run(runs / "methods" / "seed-0" / "kd-3c", list(CLASS_NAMES), iou)]  # a sweep's deeper layout
    inner = stages[0] / "predictions" / "val"  # what a stage run holds is not searched
    inner.mkdir(parents=True)
    (inner / "summary.json").write_text(json.dumps({"stage": "not-a-run"}))
    assert main(["report", str(runs)]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(s / "report.md") for s in sorted(stages)]
    assert all((s / "report.md").is_file() for s in stages) and not (inner / "report.md").exists()
    assert main(["report", str(stages[1]), str(stages[0])]) == 0  # what a shell makes of runs/quickstart/*-*
    assert capsys.readouterr().out.split() == [str(stages[1] / "report.md"), str(stages[0] / "report.md")]


def test_report_of_a_folder_without_runs_says_what_it_looked_for(tmp_path: Path, capsys) -> None:
    (tmp_path / "empty" / "deeper").mkdir(parents=True)
    assert main(["report", str(tmp_path / "empty")]) == 2
    assert "no finished stage run here or under it" in capsys.readouterr().err
