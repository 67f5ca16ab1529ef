"""The records of the shipped sweeps (results/, kept by scripts/keep-records): every record is a finished run of its
sweep file as that file and this code name runs today (a card version or a default that changed a run's identity
leaves its record stale, and this fails), made with one thread a run (the sweeps' `--jobs 2` on 2 cores), and
`distilkit sweep FILE --output results --collect` re-collects a table from them without training."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

from conftest import ROOT

RESULTS = ROOT / "results"
FOLDERS = sorted(p for p in RESULTS.iterdir() if p.is_dir()) if RESULTS.is_dir() else []


def test_there_are_records() -> None:
    assert FOLDERS, "results/ holds no sweep's records"
    assert all((ROOT / "recipes" / "sweeps" / f"{f.name}.yaml").is_file() for f in FOLDERS), \
        [f.name for f in FOLDERS]


@pytest.mark.parametrize("folder", FOLDERS, ids=[f.name for f in FOLDERS])
def test_every_record_is_a_finished_run_of_its_sweep_file(folder: Path, tmp_path: Path) -> None:
    from distilkit.sweep.runner import SweepRun

    run = SweepRun(ROOT / "recipes" / "sweeps" / f"{folder.name}.yaml", output=tmp_path, quiet=True)
    planned: dict[str, tuple[str, set[int]]] = {}  # run folder -> (stage, the seeds naming it: a shared teacher's all)
    upstream: set[str] = set()
    for (variant, seed), pipe in run.pipes.items():
        upstream.update(run.sweep.upstream_stages(variant))
        for name in [*run.sweep.upstream_stages(variant), variant]:
            planned.setdefault(pipe.run_dir(name).name, (name, set()))[1].add(seed)
    kept = sorted(p for p in folder.iterdir() if p.is_dir())
    stale = [p.name for p in kept if p.name not in planned]
    assert not stale, f"records no run of {folder.name}.yaml is named by today: {stale}"
    for record in kept:
        summary = json.loads((record / "summary.json").read_text())
        name, seeds = planned[record.name]
        assert summary["status"] == "finished" and summary["stage"] == name, record.name
        assert summary["seed"] in seeds and summary["threads"] == 1, record.name
        assert (record / "recipe.resolved.yaml").is_file(), record.name
        if summary["metric"]["name"] == "ssc":  # per-scene counts of the table's metric (a proposal stage has none)
            assert (record / "scene_counts.npz").is_file(), record.name
        if name in upstream:  # what the rest of the sweep trains against
            assert (record / "checkpoints" / "best.pt").is_file(), record.name


@pytest.mark.parametrize("folder", FOLDERS, ids=[f.name for f in FOLDERS])
def test_a_table_re_collects_from_the_records_alone(folder: Path, tmp_path: Path) -> None:
    from distilkit.cli import main

    shutil.copytree(folder, tmp_path / folder.name)
    code = main(["sweep", str(ROOT / "recipes" / "sweeps" / f"{folder.name}.yaml"), "--output", str(tmp_path),
                 "--collect", "--quiet"])
    assert code == 0
    with open(tmp_path / folder.name / "results.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    kept = sorted(p.name for p in folder.iterdir() if p.is_dir())
    assert sorted(Path(r["run_dir"]).name for r in rows) == kept  # one row a record, none left out
    for r in rows:
        summary = json.loads((folder / Path(r["run_dir"]).name / "summary.json").read_text())
        key = summary["metric"]["key"]  # miou; an upstream proposal stage's iou
        assert int(r["seed"]) == summary["seed"] and float(r[f"best_{key}"]) == pytest.approx(summary["test"]["best"][key], rel=1e-5)
    assert sorted(p.name for p in (tmp_path / folder.name).iterdir() if p.is_dir()) == kept  # nothing trained


def test_the_pages_say_what_the_records_give(tmp_path: Path) -> None:
    """The README's comparison, the reading-a-sweep tutorial and the method pages that quote a kept sweep are what
    scripts/write-comparison writes from the records' reports, word for word (each re-collected here first)."""
    import subprocess
    import sys

    from distilkit.cli import main

    for folder in FOLDERS:
        shutil.copytree(folder, tmp_path / folder.name)
        assert main(["sweep", str(ROOT / "recipes" / "sweeps" / f"{folder.name}.yaml"), "--output", str(tmp_path),
                     "--collect", "--quiet"]) == 0
    check = subprocess.run([sys.executable, str(ROOT / "scripts" / "write-comparison"), "--check", "--results",
                            str(tmp_path)], capture_output=True, text=True)
    assert check.returncode == 0, check.stdout + check.stderr
