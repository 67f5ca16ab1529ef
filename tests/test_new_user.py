"""What a new user hits first (issue 27): validate checks what a run needs, --set with wildcards, did-you-mean for
recipe keys, the student exported alone, help that teaches, adapter parameters documented, tables that read at 80
columns, file modes."""

from __future__ import annotations

import io
import json
import os
import stat
from pathlib import Path

import pytest
import torch
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT, folder_recipe, tiny_recipe
from distilkit.cli import BENCH_NAMES, EXAMPLES, build_parser, main
from distilkit.engine.train.pipeline import Pipeline
from distilkit.recipe import recipe_from_dict


def write(tmp_path: Path, recipe: dict, name: str = "r.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(recipe))
    return path


@pytest.fixture(scope="module")
def tiny_runs(tmp_path_factory: pytest.TempPathFactory):
    """One finished teacher + DSKD student run of the tiny recipe (a step each), shared by the tests that only read
    it: its teacher's checkpoint, the student exported, the results table (tests/_tiny_runs.py: trained once a
    process, with tests/test_pipeline.py's that read it)."""
    from _tiny_runs import tiny_runs

    return tiny_runs(tmp_path_factory)[1]


# -- 1. validate checks what a run will need ------------------------------------------------------------------------

def test_validate_names_a_missing_data_folder_once_and_exits_2(tmp_path, capsys) -> None:
    path = write(tmp_path, folder_recipe(tmp_path / "nowhere", train=["00"], val=["08"]))
    assert main(["validate", str(path)]) == 2
    out = capsys.readouterr()
    assert out.out.count("ok") == 0 and "no sequences/ folder" in out.err
    assert out.err.count("memory not estimated") == 1 and "data.params (train)" in out.err


@pytest.mark.xdist_group("tiny_runs")  # tests/_tiny_runs.py: one worker trains it once
def test_validate_names_a_missing_an_unreadable_and_a_misfit_checkpoint(tmp_path, capsys, tiny_runs) -> None:
    recipe = tiny_recipe(steps=1, distill=False)
    student = recipe["stages"]["teacher"]
    recipe["stages"]["from_file"] = {**student, "init": {"checkpoint": str(tmp_path / "missing.pt")}}
    path = write(tmp_path, recipe)
    assert main(["validate", str(path), "--no-memory"]) == 2
    err = capsys.readouterr().err
    assert "stages.from_file.init.checkpoint" in err and "missing.pt: no such file" in err
    (tmp_path / "garbage.pt").write_bytes(b"not a checkpoint" * 10)
    recipe["stages"]["from_file"]["init"]["checkpoint"] = str(tmp_path / "garbage.pt")
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    assert "garbage.pt: not a readable checkpoint" in capsys.readouterr().err
    # weights that do not fit: every key that does not is named (missing, unexpected, of another shape: both shapes)
    teacher = tiny_runs[0]  # the teacher stage of tiny_recipe(steps=1): the model of the recipe's teacher here
    good = torch.load(teacher.run_dir / "checkpoints" / "best.pt", weights_only=True)["student"]
    other = dict(good)
    gone, wide = [k for k, v in other.items() if v.dim() == 2][:2]
    del other[gone]
    other[wide] = torch.zeros(other[wide].shape[0] + 1, other[wide].shape[1])
    other["net.extra.weight"] = torch.zeros(3)
    torch.save(other, tmp_path / "other.pt")
    recipe["stages"]["from_file"]["init"]["checkpoint"] = str(tmp_path / "other.pt")
    recipe["stages"]["teacher_file"] = {**student, "teacher": {"checkpoint": str(tmp_path / "other.pt"),
                                                               "model": student["model"]},
                                        "distill": [{"name": "kd"}]}
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    err = capsys.readouterr().err
    assert "stages.teacher_file.teacher.checkpoint" in err and "1 unexpected: net.extra.weight" in err
    assert f"1 missing: {gone}" in err and f"1 of another shape: {wide} " in err and "(model: " in err
    # the same model's checkpoint fits; with `strict: false` only keys of another shape count
    recipe["stages"]["teacher_file"]["teacher"]["checkpoint"] = str(teacher.run_dir / "checkpoints" / "best.pt")
    recipe["stages"]["from_file"]["init"] = {"checkpoint": str(tmp_path / "other.pt"), "strict": False}
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    err = capsys.readouterr().err
    assert "from_file.init.checkpoint" in err and "stages.teacher_file" not in err and "missing:" not in err
    del other[wide]
    torch.save(other, tmp_path / "partial.pt")
    recipe["stages"]["from_file"]["init"]["checkpoint"] = str(tmp_path / "partial.pt")
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 0
    # NaN or infinite weights are refused, the key named
    poisoned = dict(good)
    poisoned[wide] = poisoned[wide].clone()
    poisoned[wide][0, 0] = float("nan")
    torch.save(poisoned, tmp_path / "nan.pt")
    recipe["stages"]["from_file"]["init"] = {"checkpoint": str(tmp_path / "nan.pt")}
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    assert f"nan.pt: {wide} holds 1 NaN or infinite values" in capsys.readouterr().err


def test_names_that_cannot_be_folder_names_are_refused(tmp_path, capsys) -> None:
    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"] = {"s" * 300: recipe["stages"]["teacher"]}
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    assert "at most 128" in capsys.readouterr().err
    recipe = tiny_recipe(steps=1, distill=False)
    recipe["name"] = "n" * 300
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"]["teacher"]["label"] = "x" * 1_000_000  # a 1 MB label: refused at once, not rendered
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    assert "at most 200" in capsys.readouterr().err


# -- 3. --set with wildcards, 4. did-you-mean ---------------------------------------------------------------------

def test_set_with_a_wildcard_sets_every_stage_and_one_that_matches_nothing_is_named(tmp_path, capsys) -> None:
    from distilkit.recipe import load_recipe, parse_overrides

    path = ROOT / "recipes" / "quickstart.yaml"
    recipe = load_recipe(path, parse_overrides(["stages.*.train.steps=4", "stages.*.distill.*.weight=2"]))
    assert {s.train.steps for s in recipe.stages.values()} == {4}
    assert [t.weight for s in recipe.stages.values() for t in s.distill] == [2, 2]
    assert main(["validate", str(path), "--no-memory", "--set", "stages.*.nothing.*.x=1"]) == 2
    assert "matches nothing" in capsys.readouterr().err
    reference = (ROOT / "docs" / "reference" / "recipe.md").read_text()
    assert "--set 'stages.*.train.steps=4'" in reference


@pytest.mark.parametrize("where,key,want", [
    ("stage", "optimiser", "optimizer"), ("train", "batchsize", "batch_size"), ("train", "step", "steps"),
    ("params", "channel", "channels")])
def test_an_unknown_key_gets_the_nearest_valid_one(tmp_path, capsys, where: str, key: str, want: str) -> None:
    recipe = tiny_recipe(steps=1, distill=False)
    stage = recipe["stages"]["teacher"]
    {"stage": stage, "train": stage["train"], "params": stage["model"]["params"]}[where][key] = 1
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    err = capsys.readouterr().err
    assert f"unknown key {key!r}; did you mean {want!r}?" in err and "valid:" in err


# -- 5. distilkit export ------------------------------------------------------------------------------------------

@pytest.mark.xdist_group("tiny_runs")  # tests/_tiny_runs.py: one worker trains it once
def test_export_writes_the_student_alone_loadable_by_torch_and_by_init(tmp_path, capsys, tiny_runs) -> None:
    from distilkit.engine.infer.export import build_exported
    from distilkit.engine.assemble.runs import load_run

    teacher, student = tiny_runs
    out = tmp_path / "exp" / "student.pt"
    assert main(["export", str(student.run_dir), "--out", str(out)]) == 0
    weights = torch.load(out, weights_only=True)
    ckpt = torch.load(student.run_dir / "checkpoints" / "best.pt", weights_only=True)
    assert set(weights) == set(ckpt["student"]) and all(torch.equal(weights[k], ckpt["student"][k]) for k in weights)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["adapter"] == "scpnet" and meta["classes"]["names"][1] == "car" and meta["weights"] == "student.pt"
    model, original = build_exported(out.with_suffix(".json")), load_run(student.run_dir)
    batch = Pipeline(recipe_from_dict(tiny_recipe(steps=1)), tmp_path / "runs", quiet=True)
    b = batch.collate([batch.dataset("test")[0]])
    with torch.no_grad():
        assert torch.equal(model(b)["logits"], original(b)["logits"])
    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"]["teacher"]["init"] = {"checkpoint": str(out)}
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 0
    (started,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs2", quiet=True).run()
    assert started.summary["status"] == "finished"
    assert main(["export", str(student.run_dir), "--out", str(tmp_path / "x.json")]) == 2


# -- 6. help that teaches, 17. adapter parameters --------------------------------------------------------------

def test_every_subcommand_help_ends_with_examples_and_bench_lists_every_bench(capsys) -> None:
    from distilkit.bench import BENCHES

    assert set(BENCH_NAMES) == set(BENCHES)
    parser = build_parser()
    commands = parser._subparsers._group_actions[0].choices  # noqa: SLF001
    for name, sub in commands.items():
        text = sub.format_help()
        assert "examples:" in text, name
        for action in sub._positionals._group_actions:  # noqa: SLF001
            assert action.help, f"{name} {action.dest}: a positional argument without a description"
    assert all(f"  {n} " in commands["bench"].format_help() for n in BENCHES)
    assert set(EXAMPLES) >= set(commands)
    assert main(["list", "task_losses"]) == 0 and "partial_ce" in capsys.readouterr().out


def test_adapter_parameters_are_documented_where_a_user_looks(tmp_path, capsys) -> None:
    reference = (ROOT / "docs" / "reference" / "recipe.md").read_text()
    assert "### scpnet" in reference and "| `frames` |" in reference and "| `geometry` |" in reference
    assert "`proposal` only from an auxiliary model" in reference
    assert main(["list", "adapters"]) == 0
    assert "seg_channels=" in capsys.readouterr().out
    with pytest.MonkeyPatch.context() as mp:  # an 80-column terminal: one block per adapter, no line past 80
        mp.setenv("COLUMNS", "80")
        assert main(["list", "adapters"]) == 0
    narrow = capsys.readouterr().out
    assert max(len(line) for line in narrow.splitlines()) <= 80
    from distilkit.registry import ADAPTERS

    assert all(f"\n{e.name}" in narrow for e in ADAPTERS) and narrow.count("│ network ") == len(list(ADAPTERS))
    assert main(["schema"]) == 0
    schema = json.loads(capsys.readouterr().out)
    rules = schema["$defs"]["ModelSpec"]["allOf"]
    scpnet = next(r for r in rules if r["if"]["properties"]["adapter"]["const"] == "scpnet")
    ref = scpnet["then"]["properties"]["params"]["$ref"].split("/")[-1]
    assert "channels" in schema["$defs"][ref]["properties"]
    # a stage that reads an input only an aux edge gives is told so
    recipe = yaml.safe_load((ROOT / "recipes" / "scribble2scene.yaml").read_text())
    del recipe["stages"]["student"]["aux"]
    assert main(["validate", str(write(tmp_path, recipe)), "--no-memory"]) == 2
    assert "a frozen auxiliary model's tap does" in capsys.readouterr().err


# -- 2. readable at 80 columns ----------------------------------------------------------------------------------

@pytest.mark.xdist_group("tiny_runs")  # tests/_tiny_runs.py: one worker trains it once
def test_the_results_table_and_the_progress_bar_keep_every_number_whole_at_80_columns(tiny_runs) -> None:
    from rich.console import Console

    from distilkit.console import stage_progress
    from distilkit.report.recipe import results_table
    from distilkit.report.scores import ScoreView, stage_row

    results = tiny_runs
    for width in (80, 200):
        console = Console(width=width, record=True, file=io.StringIO())
        console.print(results_table(results, "a note under the table"))
        text = console.export_text()
        for r in results:
            row = stage_row(r.summary)
            view: ScoreView = row["view"]
            for c in view.headline:
                assert view.fmt(c, row["best"][c[0]]) in text, (width, c)
        assert "status" in text and "trained" in text and "a note under the table" in text
        assert "…" not in text.replace("...", "")
    def line(bar) -> str:  # the bar as an 80-column terminal shows it
        out = Console(width=80, record=True, file=io.StringIO())
        out.print(bar.progress.make_tasks_table(bar.progress.tasks))
        return out.export_text()

    quiet = Console(file=io.StringIO(), width=80)
    with stage_progress(quiet, "a_stage_with_a_rather_long_name_that_goes_on") as bar:
        bar(1, 100, {"loss": 1.5, "kd_distillation_dpo": 0.01, "lr": 0.001})
        first = line(bar)
        bar(100, 100, {"loss": 1.5, "kd_distillation_dpo": 0.01, "lr": 0.001})
        done = line(bar)
        bar.evaluation(3, 16)
        evaluating = line(bar)
    assert "1/100" in first and "it/s" not in first  # no rate from a single step
    assert "100/100" in done and "it/s" in done and "1000000000" not in done
    assert "eval 3/16" in evaluating


# -- 15. file modes -----------------------------------------------------------------------------------------------

def test_atomic_writes_honour_the_umask(tmp_path) -> None:
    from distilkit.files import atomic_write_text

    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.txt", "x")
        assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644
        os.umask(0o027)
        atomic_write_text(tmp_path / "b.txt", "x")
        assert stat.S_IMODE((tmp_path / "b.txt").stat().st_mode) == 0o640
    finally:
        os.umask(old)
