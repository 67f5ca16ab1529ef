"""What the console tells a user (issue 44, item 6), read as the user sees it: `run --stage` of a finished stage
prints its scores and where its report is, a resume says so, every command's help fits 80 columns, every option has
help, `list` keeps every cell whole, the sparse bench's note says which way its ratio goes."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import ROOT, tiny_recipe
from distilkit.cli import EXAMPLES, build_parser, main


def write(tmp_path: Path, recipe: dict) -> Path:
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return path


# -- run: a finished stage's scores, a resume ------------------------------------------------------------------------

def test_run_stage_of_a_finished_stage_prints_its_scores_and_its_report(tmp_path, capsys, monkeypatch) -> None:
    from distilkit.report.scores import ScoreView, stage_row

    monkeypatch.setenv("COLUMNS", "120")
    path = write(tmp_path, tiny_recipe(steps=1))
    out = str(tmp_path / "runs")
    assert main(["run", str(path), "-o", out, "--stage", "teacher"]) == 0
    capsys.readouterr()
    assert main(["run", str(path), "-o", out, "--stage", "teacher"]) == 0  # finished: reused
    text = capsys.readouterr().out
    (run_dir,) = (tmp_path / "runs" / "tiny").glob("teacher-*")
    summary = json.loads((run_dir / "summary.json").read_text())
    row = stage_row(summary)
    view: ScoreView = row["view"]
    assert "reused" in text
    for column in view.headline:  # the scores a whole run's table shows
        assert view.fmt(column, row["best"][column[0]]) in text, column
    assert f"stage teacher report: {run_dir / 'report.md'}" in text and (run_dir / "report.md").is_file()
    assert "student" not in text  # only the stage asked for (and what it needs)


def test_a_resumed_stage_says_so_on_the_console_and_from_which_checkpoint(tmp_path, capsys, monkeypatch) -> None:
    import distilkit.report.run

    monkeypatch.setattr(distilkit.report.run, "write_run_report", lambda run_dir: None)  # no test here reads it
    path = write(tmp_path, tiny_recipe(steps=3, distill=False))
    out = str(tmp_path / "runs")
    assert main(["run", str(path), "-o", out, "--stop-after", "1"]) == 0
    assert "resumed" not in capsys.readouterr().out
    assert main(["run", str(path), "-o", out, "--stop-after", "2"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if "resumed" in line]
    assert lines == ["stage teacher: resumed from step 1 of 3 (last.pt)"]
    (last,) = (tmp_path / "runs" / "tiny").glob("teacher-*/checkpoints/last.pt")
    last.write_bytes(last.read_bytes()[:100])  # cut short: the run goes back to the one before
    assert main(["run", str(path), "-o", out]) == 0
    text = capsys.readouterr().out
    assert "stage teacher: resumed from step 1 of 3 (last.prev.pt)" in text
    assert "it is not a complete PyTorch file (100 bytes)" in " ".join(text.split())  # rich wraps the line


# -- help: 80 columns, every option described -----------------------------------------------------------------------

def parsers(parser: argparse.ArgumentParser, name: str = "distilkit"):
    """Every command's and subcommand's parser, with its name."""
    yield name, parser
    for action in parser._actions:  # noqa: SLF001
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            for sub, p in action.choices.items():
                yield from parsers(p, f"{name} {sub}")


def examples_in(help_text: str) -> list[str]:
    """The commands of a help's examples, as a shell reads them: continued lines joined, comments dropped."""
    block = help_text.split("\nexamples:\n", 1)[1]
    joined = re.sub(r" \\\n\s+", " ", block)
    return [line.strip() for line in joined.splitlines() if line.strip() and not line.strip().startswith("#")]


def test_every_help_fits_80_columns_and_its_examples_are_the_same_commands(monkeypatch) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    seen = 0
    for name, parser in parsers(build_parser()):
        text = parser.format_help()
        long = [line for line in text.splitlines() if len(line) > 80]
        assert not long, (name, long)
        command = name.removeprefix("distilkit ")
        if command in EXAMPLES:
            want = [" ".join(e.split("  #")[0].split()) for e in EXAMPLES[command]]
            assert [" ".join(e.split()) for e in examples_in(text)] == want, name
            seen += 1
    assert seen == len(EXAMPLES)
    env = {**os.environ, "COLUMNS": "80"}  # as a terminal shows it
    shown = subprocess.run([sys.executable, "-m", "distilkit", "sweep", "--help"], capture_output=True, text=True,
                           env=env, cwd=ROOT, check=True).stdout
    assert max(map(len, shown.splitlines())) <= 80 and " \\\n      --" in shown


def test_every_option_of_every_command_has_help(capsys) -> None:
    for name, parser in parsers(build_parser()):
        for action in parser._actions:  # noqa: SLF001
            if action.option_strings and action.help != argparse.SUPPRESS:
                assert action.help, f"{name} {'/'.join(action.option_strings)}: no help"
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--device {cpu,cuda} where both forms are timed: cpu (default" in text


# -- list: every cell whole at 80 and 120 columns -------------------------------------------------------------------

def table_rows(text: str) -> dict[str, dict[str, list[str]]]:
    """The rows of each table ``distilkit list`` printed, by kind and name: the text of each cell, its lines joined
    without whitespace (a word folded over two lines is whole again)."""
    tables: dict[str, dict[str, list[str]]] = {}
    kind, row = "", None
    for line in text.splitlines():
        if line.strip() and not line.startswith(("│", "┃", "┏", "┡", "└", "┗")):
            kind, row = line.strip(), None
            tables[kind] = {}
        elif line.startswith("│"):
            cells = [c.strip() for c in line.strip("│").split("│")]
            if cells[0]:
                row = [cells[0], *cells[1:]]
                tables[kind][str(len(tables[kind]))] = row
            elif row is not None:
                row[:] = [a + b for a, b in zip(row, cells)]
    return {k: {"".join(r[0].split()): ["".join(c.split()) for c in r] for r in rows.values()}
            for k, rows in tables.items()}


@pytest.mark.parametrize("width", [80, 120])
def test_list_keeps_every_cell_whole(width, capsys, monkeypatch) -> None:
    from distilkit.registry import ALL_REGISTRIES

    monkeypatch.setenv("COLUMNS", str(width))
    assert main(["list"]) == 0
    text = capsys.readouterr().out
    assert "…" not in text and max(map(len, text.splitlines())) <= width
    tables = table_rows(text)
    checked = 0
    for kind, reg in ALL_REGISTRIES.items():
        if kind == "adapters":  # at 80 columns a block per adapter (tests/test_new_user.py)
            continue
        for entry in reg:
            also = reg.aliases_of(entry.name)
            name = "".join((entry.name + (f" (also {', '.join(also)})" if also else "")).split())
            cells = tables[kind][name]
            paper = "" if entry.paper == "—" else entry.paper
            want = [entry.description + paper] if width < 120 else [entry.description, entry.paper]
            assert cells[1:1 + len(want)] == ["".join(w.split()) for w in want], (kind, entry.name)
            checked += 1
    assert checked > 40


# -- the sparse bench's note ------------------------------------------------------------------------------------------

def test_the_sparse_bench_says_which_way_its_ratio_goes() -> None:
    from distilkit.bench.sparse import compared

    assert compared(10.0, 25.0) == "2.5x faster"  # 10 ms against dense conv3d's 25 ms
    assert compared(25.0, 10.0) == "2.5x slower"  # was "0.4x faster"
    assert compared(10.0, 10.0) == "1.0x faster"
