"""Recipes, `distilkit validate`, `list`, `schema`, cheap imports and the registry."""

from __future__ import annotations

import math
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT, tiny_recipe
from distilkit.cli import main
from distilkit.registry import OBJECTIVES, Registry
from distilkit.errors import UnknownNameError


def write(tmp_path: Path, data, name: str = "r.yaml") -> Path:
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return p


def validate(path: Path, capsys) -> tuple[int, str]:
    code = main(["validate", str(path), "--static"])  # the memory estimate: tests/test_memory.py; the terms' dry
    # step: tests/test_validate_first_step.py
    captured = capsys.readouterr()
    return code, captured.out + captured.err


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """A SemanticKITTI-format folder (sequences 00 and 08, images, ScribbleSC scribbles) for the recipes that read
    one: validate checks the data is there. This process's exported folder (tests/_camera_kitti.py), read only."""
    from _camera_kitti import camera_kitti

    return camera_kitti(tmp_path_factory)


@pytest.mark.parametrize("recipe", sorted([*(ROOT / "recipes").glob("*.yaml"), *(ROOT / "recipes" / "paper").glob("*.yaml")]),
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_shipped_recipes_validate(recipe: Path, capsys, folder) -> None:
    data = yaml.safe_load(recipe.read_text()).get("data", {})
    if "root" in data.get("params", {}):  # a real-data recipe: pointed at a folder, as its header says
        extra = ["--set", f"data.params.root={folder}", 'data.params.train=["00"]', 'data.params.val=["08"]',
                 *(["data.params.scribbles=scribblesc"] if "scribbles" in data["params"] else [])]
        code = main(["validate", str(recipe), "--static", *extra])  # the paper networks' dry steps take minutes here
        captured = capsys.readouterr()
        code, out = code, captured.out + captured.err
    else:
        code, out = validate(recipe, capsys)
    assert code == 0 and "ok" in out, out


def test_misspelled_objective_suggests(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["student"]["distill"][0]["name"] = "dskdd"
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2
    assert "stages.student.distill[0].name" in out and "did you mean 'dskd'" in out
    assert "Traceback" not in out


def test_wrong_type_names_the_field(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["student"]["distill"][0]["weight"] = "heavy"
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "stages.student.distill[0].weight" in out


def test_unknown_key_and_bad_adapter_param(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["teacher"]["trian"] = {}
    r["stages"]["teacher"]["model"]["params"]["chanels"] = 3
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2
    assert "stages.teacher.trian: unknown key" in out


def test_bad_adapter_param_names_path(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["teacher"]["model"]["params"]["chanels"] = 3
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "stages.teacher.model.params.chanels: unknown key" in out


def test_malformed_yaml(tmp_path, capsys) -> None:
    code, out = validate(write(tmp_path, "name: x\nstages: [\n  a: b\n"), capsys)
    assert code == 2 and "malformed YAML" in out and "line" in out


def test_python_tag_is_rejected_and_never_executed(tmp_path, capsys) -> None:
    marker = tmp_path / "pwned"
    text = f"name: x\nseed: !!python/object/apply:os.system ['touch {marker}']\nstages: {{}}\n"
    code, out = validate(write(tmp_path, text), capsys)
    assert code == 2 and "python/object/apply" in out
    assert not marker.exists()


def test_taps_the_adapter_does_not_provide(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["student"]["distill"][0]["taps"] = {"student": "logits"}
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "tap 'logits'" in out and "sparse_features" in out
    r["stages"]["student"]["distill"][0]["taps"] = {"student": "nope"}
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "has no tap 'nope'" in out


def test_unknown_teacher_stage_and_missing_teacher(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["student"]["teacher"] = {"from": "teachr"}
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "stages.student.teacher.from" in out and "did you mean 'teacher'" in out
    r = tiny_recipe()
    del r["stages"]["student"]["teacher"]
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "need a `teacher`" in out


def test_too_many_frames_for_the_data(tmp_path, capsys) -> None:
    r = tiny_recipe()
    r["stages"]["teacher"]["model"]["params"]["frames"] = 9
    code, out = validate(write(tmp_path, r), capsys)
    assert code == 2 and "stages.teacher.model.params.frames" in out


def test_registry_rejects_duplicates_and_suggests() -> None:
    reg: Registry[object] = Registry("thing")
    reg.add("alpha", 1, description="a")
    with pytest.raises(ValueError, match="already registered"):
        reg.add("alpha", 2, description="b")
    reg.add("alpha", 2, description="b", override=True)
    assert reg.get("alpha") == 2
    with pytest.raises(UnknownNameError, match="did you mean 'alpha'"):
        reg.get("alpah")
    assert OBJECTIVES.entry("dskd").meta["default_weight"] == 3000.0


def test_list_shows_components(capsys) -> None:
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ("scpnet", "js3cnet", "dskd", "synthetic-lidar", "ssc", "lovasz"):
        assert name in out
    assert "SCPNet" in out


def test_schema_is_json_and_docs_are_in_sync(capsys) -> None:
    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert "stages" in schema["properties"] and schema["additionalProperties"] is False
    assert main(["schema", "--markdown"]) == 0
    generated = capsys.readouterr().out
    assert (ROOT / "docs" / "reference" / "recipe.md").read_text() == generated, \
        "docs/reference/recipe.md is stale: run `distilkit schema --markdown > docs/reference/recipe.md`"


def test_help_and_import_do_not_import_torch() -> None:
    code = ("import sys, distilkit, distilkit.cli\n"
            "try:\n    distilkit.cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
            "assert 'torch' not in sys.modules, 'torch imported'\nprint('clean')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "clean" in out.stdout and "usage: distilkit" in out.stdout


def test_python_dash_m_works() -> None:
    out = subprocess.run([sys.executable, "-m", "distilkit", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and "distilkit" in out.stdout


@pytest.mark.parametrize("argv", [["list"], ["sweep", "recipes/sweeps/l2cocc.yaml", "--plan"]],
                         ids=["rich output", "plain print"])
def test_output_piped_into_a_reader_that_has_gone_ends_quietly(argv: list[str]) -> None:
    """`distilkit sweep ... --plan | head -1`: the reader closes the pipe before the command is done writing; status
    1 and no traceback, whether the output went through rich's console or plain print."""
    import os

    read, write = os.pipe()
    os.close(read)  # the reader is gone before a byte is written
    try:
        out = subprocess.run([sys.executable, "-m", "distilkit", *argv], stdout=write, stderr=subprocess.PIPE,
                             text=True, timeout=120, cwd=ROOT)
    finally:
        os.close(write)
    assert out.returncode == 1, out.stderr
    assert "Traceback" not in out.stderr and "BrokenPipeError" not in out.stderr, out.stderr


@pytest.fixture
def no_full_collections(monkeypatch) -> None:
    """The bench's memory column starts each timing with a full garbage collection (two a case), which walks every
    object of the test process: a tenth of a second or more a call, about 1 s of CPU over this module's four
    benches. These tests check the timings, the values and the table, not the peak memory, so the bench module's
    collection is a no-op here (`distilkit bench` itself still collects)."""
    import types

    import distilkit.bench.base

    monkeypatch.setattr(distilkit.bench.base, "gc", types.SimpleNamespace(collect=lambda *args: 0))


def test_bench_quick_reports_a_speedup(capsys, no_full_collections) -> None:
    from distilkit.bench import run_bench

    rows = run_bench(["dskd"], quick=True, repeat=1)
    out = capsys.readouterr().out
    assert "dskd" in out and "speed-up" in out
    naive_rows = [r for r in rows if "speedup" in r]
    assert naive_rows and naive_rows[0]["rel_err"] < 1e-4
    assert main(["bench", "nope"]) == 2


def test_losses_import_costs_only_torch() -> None:
    code = ("import sys, distilkit.losses as L\n"
            "heavy = [m for m in ('pydantic', 'yaml', 'rich', 'matplotlib', 'scipy', 'torchvision') if m in sys.modules]\n"
            "assert not heavy, heavy\nprint(L.dskd.__doc__.splitlines()[0])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "DSKD" in out.stdout


def test_bench_sampler_builds_lidiff_through_the_registry_and_times_both_step_counts(capsys,
                                                                                    no_full_collections) -> None:
    from distilkit.bench import run_bench

    (row,) = run_bench(["sampler"], quick=True, repeat=1)
    assert row["fast_ms"] > 0 and row["naive_ms"] > 0 and "rel_err" not in row  # different outputs: no error column
    assert "sampler 8 vs 50 steps" in capsys.readouterr().out


def test_set_overrides_recipe_fields_by_dotted_path_and_is_validated_like_the_file(tmp_path: Path, capsys) -> None:
    from conftest import tiny_recipe

    path = write(tmp_path, tiny_recipe(steps=1))
    out = tmp_path / "runs"
    assert main(["run", str(path), "-o", str(out), "-q", "--stage", "teacher", "--no-wait",
                 "--set", "stages.teacher.optimizer.lr=0.01", "stages.teacher.model.params.point_mlp=[6]"]) == 0
    (run,) = (out / "tiny").glob("teacher-*")
    resolved = yaml.safe_load((run / "recipe.resolved.yaml").read_text())
    assert resolved["optimizer"]["lr"] == 0.01 and resolved["model"]["params"]["point_mlp"] == [6]
    assert resolved["overrides"] == {"stages.teacher.optimizer.lr": 0.01, "stages.teacher.model.params.point_mlp": [6]}
    assert main(["run", str(path), "-o", str(out), "-q", "--stage", "teacher"]) == 0  # without: another identity
    assert len(list((out / "tiny").glob("teacher-*"))) == 2
    capsys.readouterr()
    cases = {  # each: one line naming what is wrong
        "stages.teacher.optimizer.lr=-1": "stages.teacher.optimizer.lr",
        "stages.teachr.train.steps=3": "no stage 'teachr'; did you mean 'teacher'?",
        "stages.teacher.train.steps": "expected PATH=VALUE",
        "stages..steps=3": "expected PATH=VALUE",
    }
    for item, message in cases.items():
        assert main(["validate", str(path), "--no-memory", "--set", item]) == 2, item
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and "Traceback" not in err, (item, err)
    assert main(["validate", str(path), "--no-memory", "--set", "stages.student.distill.0.weight=3"]) == 0


def test_bench_loader_times_the_same_steps_with_and_without_workers(capsys, no_full_collections, monkeypatch) -> None:
    """... and leaves nothing behind: the folder of its run and data is removed at the end."""
    import distilkit.bench.base as base
    from distilkit.bench import run_bench

    made = []
    real = base.scratch_dir
    monkeypatch.setattr(base, "scratch_dir", lambda prefix: made.append(real(prefix)) or made[-1])
    monkeypatch.setattr("distilkit.bench.training.scratch_dir", base.scratch_dir)
    (row,) = run_bench(["loader"], quick=True, repeat=1)
    assert "loader: 2 workers vs none" in capsys.readouterr().out
    assert row["fast_ms"] > 0 and row["naive_ms"] > 0 and math.isfinite(row["value"])
    assert made and all(p.parent.name.startswith("distilkit-bench-") and not p.parent.exists() for p in made)
    assert base.SCRATCH == []


def test_bench_camera_times_the_camera_student_with_and_without_rgo2d(capsys, no_full_collections) -> None:
    from distilkit.bench import run_bench

    (row,) = run_bench(["camera"], quick=True, repeat=1)
    assert "camera student: no KD vs RGO²D" in capsys.readouterr().out
    assert row["fast_ms"] > 0 and row["naive_ms"] > 0 and math.isfinite(row["value"])


def test_the_datasets_page_is_in_sync(capsys) -> None:
    assert main(["list", "datasets", "--markdown"]) == 0
    generated = capsys.readouterr().out
    assert "| `val` |" in generated and "FolderCameraParams" in generated and "\\| \"valid\"" in generated
    assert (ROOT / "docs" / "reference" / "datasets.md").read_text() == generated, \
        "docs/reference/datasets.md is stale: run `distilkit list datasets --markdown > docs/reference/datasets.md`"
