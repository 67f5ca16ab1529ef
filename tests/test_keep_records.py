"""scripts/keep-records: a sweep's finished runs kept as records (summary, resolved recipe, per-scene counts, and an
upstream stage's best.pt), unfinished ones left out, a changed record reported by --check."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "keep-records"


@pytest.fixture(scope="module")
def keep():
    loader = importlib.machinery.SourceFileLoader("keep_records", str(SCRIPT))
    spec = importlib.util.spec_from_loader("keep_records", loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def _run(root: Path, name: str, status: str = "finished", upstream: dict[str, str] | None = None,
         best: bool = True, extra: str = "") -> Path:
    run = root / name
    (run / "checkpoints").mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({"status": status, "stage": name}))
    ups = "".join(f"  {k}: {v}\n" for k, v in (upstream or {}).items())
    (run / "recipe.resolved.yaml").write_text(
        "name: q\nstages:\n  upstream:\n    nested: not-this\n" + extra
        + (f"upstream:\n{ups}" if ups else "upstream: {}\n") + "files: {}\n")
    (run / "scene_counts.npz").write_bytes(b"counts " + name.encode())
    (run / "metrics.jsonl").write_text("{}\n")
    if best:
        (run / "checkpoints" / "best.pt").write_bytes(b"weights " + name.encode())
        (run / "checkpoints" / "last.pt").write_bytes(b"state " + name.encode())
    return run


def test_keeps_finished_runs_and_the_upstream_weights(tmp_path: Path, keep, capsys) -> None:
    sweep = tmp_path / "runs" / "qm"
    _run(sweep, "teacher-abc")
    _run(sweep, "kd_4-111", upstream={"teacher": "abc"})
    _run(sweep, "none-222")
    _run(sweep, "dist_3-333", status="running", upstream={"teacher": "abc"})
    assert keep.upstream_hashes(sweep) == ({"abc"}, False)
    assert keep.main([str(sweep), "--to", str(tmp_path / "results")]) == 0
    kept = tmp_path / "results" / "qm"
    assert sorted(p.name for p in kept.iterdir()) == ["kd_4-111", "none-222", "teacher-abc"]
    assert (kept / "teacher-abc" / "checkpoints" / "best.pt").read_bytes() == b"weights teacher-abc"
    assert not (kept / "kd_4-111" / "checkpoints").exists()  # a variant's weights stay behind
    assert not (kept / "teacher-abc" / "checkpoints" / "last.pt").exists()  # no edge reads it
    assert not (kept / "none-222" / "metrics.jsonl").exists()
    for f in keep.FILES:
        assert (kept / "kd_4-111" / f).read_bytes() == (sweep / "kd_4-111" / f).read_bytes()
    assert "copied 3 new" in capsys.readouterr().out


def test_an_upstream_run_is_found_by_its_identity_whatever_its_stage_and_edge(tmp_path: Path, keep) -> None:
    """The edge (``init:``) and the stage (``big_teacher``) differ in name, the hash is all digits (YAML quotes it),
    and an edge reads the last checkpoint: both of its checkpoints are kept."""
    sweep = tmp_path / "runs" / "qm"
    _run(sweep, "big_teacher-0123456789")
    _run(sweep, "student-222", upstream={"init": "'0123456789'"}, extra="  init:\n    which: last\n")
    assert keep.upstream_hashes(sweep) == ({"0123456789"}, True)
    assert keep.main([str(sweep), "--to", str(tmp_path / "results")]) == 0
    kept = tmp_path / "results" / "qm" / "big_teacher-0123456789" / "checkpoints"
    assert sorted(p.name for p in kept.iterdir()) == ["best.pt", "last.pt"]
    assert not (tmp_path / "results" / "qm" / "student-222" / "checkpoints").exists()


def test_check_reports_a_changed_record_and_copies_nothing(tmp_path: Path, keep, capsys) -> None:
    sweep = tmp_path / "runs" / "qm"
    _run(sweep, "none-222")
    to = tmp_path / "results"
    assert keep.main([str(sweep), "--to", str(to)]) == 0
    assert keep.main([str(sweep), "--to", str(to), "--check"]) == 0  # nothing differs
    (sweep / "none-222" / "summary.json").write_text(json.dumps({"status": "finished", "stage": "other"}))
    capsys.readouterr()
    assert keep.main([str(sweep), "--to", str(to), "--check"]) == 1
    out = capsys.readouterr().out
    assert "differs: none-222" in out and "would copy 0 new and 1 changed" in out
    assert json.loads((to / "qm" / "none-222" / "summary.json").read_text())["stage"] == "none-222"
    assert keep.main([str(sweep), "--to", str(to)]) == 0  # without --check the record is replaced
    assert json.loads((to / "qm" / "none-222" / "summary.json").read_text())["stage"] == "other"


def test_a_missing_folder_is_an_error(tmp_path: Path, keep, capsys) -> None:
    assert keep.main([str(tmp_path / "nope")]) == 2
    assert "no such folder" in capsys.readouterr().err
