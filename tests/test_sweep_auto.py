"""``distilkit sweep --seeds auto`` (issue 59, item 6): seeds added in rounds until every method's corrected interval
is narrower than the target or the seed limit is reached; the rule reads widths only, never signs; the report says
which method stopped for which reason."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from distilkit.cli import main
from distilkit.sweep.adaptive import next_seeds, verdicts, widths
from test_sweep import write_sweep

VIEW = SimpleNamespace(main=("miou", "mIoU", 100.0))


def _row(label: str, delta: list[float], ci: tuple[float, float], sim: tuple[float, float] | None = None) -> dict:
    row = {"label": label, "delta": delta, "delta_ci": ci, "view": VIEW, "chosen": True}
    if sim is not None:
        row["sim_ci"] = sim
    return row


def test_widths_are_the_corrected_intervals_in_the_tables_units_and_ignore_the_sign() -> None:
    rows = [_row("none", [], (math.nan, math.nan)),
            _row("kd", [0.01, 0.02], (-0.01, 0.03), sim=(-0.02, 0.04)),  # the simultaneous interval when there is one
            _row("pkt", [-0.01, -0.02], (-0.03, 0.01)),  # a lone method: its own interval
            {**_row("kd_1", [0.0, 0.1], (-1.0, 1.0)), "chosen": False}]  # a weight not chosen: not a method
    assert widths(rows) == pytest.approx({"kd": 6.0, "pkt": 4.0})
    flipped = [_row("kd", [-0.01, -0.02], (-0.03, 0.01), sim=(-0.04, 0.02))]  # the mirror image: the same width
    assert widths(flipped)["kd"] == pytest.approx(widths(rows)["kd"])


def test_next_seeds_adds_the_next_integers_up_to_the_limit() -> None:
    assert next_seeds([0, 1, 2], 2, 10) == [0, 1, 2, 3, 4]
    assert next_seeds([0, 5], 3, 4) == [0, 5, 6, 7]
    assert next_seeds([0, 1, 2, 3], 2, 4) == [0, 1, 2, 3]


def test_verdicts_say_which_stopped_for_which_reason() -> None:
    history = [(4, {"kd": 5.0, "dist": 2.5}), (6, {"kd": 3.5, "dist": 1.9})]
    kd, dist = verdicts(history, 3.0, 6)
    assert kd.startswith("kd: 3.50 wide at 6 seeds — the limit of 6 seeds stopped it")
    assert dist.startswith("dist: interval narrower than 3 at 4 seeds")


def test_auto_runs_rounds_until_the_limit_and_stops_at_once_when_the_target_is_met(tmp_path: Path, capsys) -> None:
    path = write_sweep(tmp_path)  # seeds [0, 1], variants none and DSKD, one step each
    out = tmp_path / "runs"
    # a target no interval meets: rounds of one seed until three have run
    assert main(["sweep", str(path), "-o", str(out), "--seeds", "auto", "--target-width", "1e-9", "--max-seeds", "3",
                 "--seed-step", "1"]) == 0
    said = " ".join(capsys.readouterr().out.split())
    assert "--seeds auto: 2 seeds, 1 method(s) wider than 1e-09: DSKD" in said
    assert "--seeds auto: 3 seeds, 1 method(s) wider" in said
    root = out / "sw"
    assert sorted(p.parent.name.split("-")[0] for p in root.glob("dskd-*/summary.json")) == ["dskd"] * 3
    md = " ".join((root / "results.md").read_text().split())
    assert "Seeds chosen by `--seeds auto` (0, 1, 2)" in md and "the rule read the widths only" in md
    assert "DSKD: " in md and "the limit of 3 seeds stopped it, not the target 1e-09" in md
    # a target every interval meets: the first round is the last, every run reused
    before = {p: p.stat().st_mtime for p in root.glob("*/summary.json")}
    assert main(["sweep", str(path), "-o", str(out), "--seeds", "auto", "--target-width", "1e9", "--max-seeds", "6",
                 "-q"]) == 0
    md = " ".join((root / "results.md").read_text().split())
    assert "Seeds chosen by `--seeds auto` (0, 1)" in md and "DSKD: interval narrower than 1e+09 at 2 seeds" in md
    assert {p: p.stat().st_mtime for p in root.glob("*/summary.json")} == before


@pytest.mark.parametrize("argv, words", [
    (["--seeds", "auto"], "with --target-width W"),
    (["--seeds", "auto", "3", "--target-width", "2"], "give `auto` alone"),
    (["--seeds", "auto", "--target-width", "2", "--plan"], "--seeds auto runs locally"),
    (["--target-width", "2"], "--target-width goes with --seeds auto"),
    (["--seeds", "auto", "--target-width", "0"], "--target-width must be > 0")])
def test_auto_refuses_what_it_cannot_do_with_one_line(tmp_path: Path, capsys, argv, words) -> None:
    path = write_sweep(tmp_path)
    assert main(["sweep", str(path), "-o", str(tmp_path / "runs"), *argv]) == 2
    assert words in capsys.readouterr().err
    assert not (tmp_path / "runs" / "sw").exists() or not list((tmp_path / "runs" / "sw").glob("*/summary.json"))


def test_a_seed_that_is_not_a_number_is_named(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["sweep", str(write_sweep(tmp_path)), "--seeds", "0", "one"])
    assert "a seed is an integer or `auto`, got 'one'" in capsys.readouterr().err
