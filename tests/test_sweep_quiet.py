"""`distilkit sweep -q`: quiet means no progress chatter; the comparison table it ran for is still printed."""

from __future__ import annotations

from pathlib import Path

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from test_sweep import write_sweep
from distilkit.cli import main


def test_a_quiet_sweep_prints_its_table_and_no_progress(tmp_path: Path, capsys) -> None:
    path = write_sweep(tmp_path, seeds=[0], variants={"none": {"label": "no distillation", "distill": []}})
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "sw: seeds" in printed and "no distillation" in printed  # the table, its title and its row
    assert f"results report: {out / 'sw' / 'results.md'}" in " ".join(printed.split())
    assert "variants ×" not in printed and "sweep finished in" not in printed  # no chatter
    assert main(["sweep", str(path), "-o", str(out), "-q", "--collect"]) == 0  # collecting alone: the same table
    assert "no distillation" in capsys.readouterr().out
