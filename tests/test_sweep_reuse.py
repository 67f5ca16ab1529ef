"""`distilkit sweep FILE --reuse DIR`: a table drawn from a larger comparison reads that comparison's finished runs
of the same configuration (by hash), under its own variant names, and trains none of them."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from distilkit.cli import main
from distilkit.errors import DistilkitError
from distilkit.sweep.reuse import reuse_runs
from distilkit.sweep.runner import SweepRun
from test_sweep import write_sweep


def _subset(tmp_path: Path, weight: float) -> Path:
    """The paper's table: another name, its own variant names; the DSKD row at ``weight``."""
    spec = yaml.safe_load((tmp_path / "sweep.yaml").read_text())
    spec["name"] = "table"
    spec["variants"] = {"none": {"distill": []},
                        "dskd_paper": {"label": "DSKD (paper)", "distill": [{"name": "dskd", "weight": weight}]}}
    path = tmp_path / f"table_{weight}.yaml"
    path.write_text(yaml.safe_dump(spec, sort_keys=False))
    return path


def test_the_same_runs_are_copied_under_the_tables_names_and_nothing_trains(tmp_path: Path, capsys) -> None:
    out = tmp_path / "runs"
    assert main(["sweep", str(write_sweep(tmp_path)), "-o", str(out), "-q"]) == 0
    big = out / "sw"
    same = _subset(tmp_path, 10)  # the comparison's DSKD weight: the same runs
    assert main(["sweep", str(same), "-o", str(out), "--collect", "-q", "--reuse", str(big)]) == 0
    assert "--reuse: 6 finished runs of the same configuration copied" in capsys.readouterr().err  # 4 + 2 teachers
    table = out / "table"
    for seed in (0, 1):
        run = SweepRun(same, out, quiet=True)
        mine, theirs = run.pipes["dskd_paper", seed].run_dir("dskd_paper"), None
        theirs = next(big.glob(f"dskd-{mine.name.rsplit('-', 1)[1]}"))
        assert json.loads((mine / "summary.json").read_text()) == json.loads((theirs / "summary.json").read_text())
    rows = {line.split(",")[0] for line in (table / "results.csv").read_text().splitlines()[1:]}
    assert rows == {"none", "dskd_paper", "teacher"}
    # the copies are runs like any other: a second call copies nothing and a plain sweep trains nothing
    assert reuse_runs(SweepRun(same, out, quiet=True), [big]) == []
    before = {p: p.stat().st_mtime for p in table.glob("*/summary.json")}
    assert main(["sweep", str(same), "-o", str(out), "-q"]) == 0
    assert {p: p.stat().st_mtime for p in table.glob("*/summary.json")} == before


def test_another_configuration_is_not_reused_and_a_stopped_run_is_left_to_resume(tmp_path: Path) -> None:
    out = tmp_path / "runs"
    assert main(["sweep", str(write_sweep(tmp_path, seeds=[0])), "-o", str(out), "-q"]) == 0
    other = SweepRun(_subset(tmp_path, 30), out, quiet=True)  # another weight: another hash
    stopped = other.pipes["none", 0].run_dir("none")
    (stopped / "checkpoints").mkdir(parents=True)  # a stopped run of the same name: resumed, not overwritten
    copied = reuse_runs(other, [out / "sw"])
    assert sorted(t.name.split("-")[0] for _, t in copied) == ["teacher"]
    assert not other.pipes["dskd_paper", 0].run_dir("dskd_paper").exists()
    assert not (stopped / "summary.json").exists()
    with pytest.raises(DistilkitError, match="--reuse .*nowhere: no such folder"):
        reuse_runs(other, [tmp_path / "nowhere"])
