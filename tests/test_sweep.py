"""distilkit sweep: variants of one stage over seeds, upstream stages shared, resumed, planned for a cluster."""

from __future__ import annotations

import csv
import shlex
from pathlib import Path

import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.cli import main
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.recipe import load_recipe
from distilkit.report import plots
from distilkit.sweep.runner import SweepRun
from distilkit.sweep.spec import load_sweep

ROOT = Path(__file__).resolve().parents[1]
RENDER = plots.save  # matplotlib's rendering, taken before tests/conftest.py's autouse fixture replaces it


def write_sweep(tmp_path: Path, **extra) -> Path:
    base = tiny_recipe(steps=1)
    base["stages"]["student"].pop("distill")
    base["stages"]["student"].pop("teacher")
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(base))
    sweep = {"schema_version": 1, "name": "sw", "recipe": "base.yaml", "stage": "student", "teacher": "teacher",
             "seeds": [0, 1], "variants": {"none": {"distill": []},
                                           "dskd": {"label": "DSKD", "distill": [{"name": "dskd", "weight": 10}]}},
             **extra}
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep, sort_keys=False))
    return path


def summaries(root: Path) -> dict[str, float]:
    return {p.parent.name: p.stat().st_mtime for p in root.glob("*/summary.json")}


def test_a_sweep_runs_every_variant_and_seed_shares_teachers_and_resumes(tmp_path: Path, monkeypatch) -> None:
    """Every variant and seed is run (a teacher per seed), results.csv/.md hold each run and the paired difference,
    results.png is rendered (for real: the runs' own figures, which the test does not look at, are not), and a
    second start reuses everything."""
    closed = plots.save  # tests/conftest.py's stand-in: closes the figure, writes an empty file
    monkeypatch.setattr(plots, "save", lambda fig, p: (RENDER if p.name.startswith("results") else closed)(fig, p))
    path = write_sweep(tmp_path)
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "-q"]) == 0
    root = out / "sw"
    runs = summaries(root)
    # one teacher per seed (upstream: per_seed), one run per variant and seed; the none variant has no teacher
    assert sorted(n.split("-")[0] for n in runs) == ["dskd", "dskd", "none", "none", "teacher", "teacher"]
    with open(root / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted((r["variant"], r["seed"], r["role"]) for r in rows) == [
        ("dskd", "0", "variant"), ("dskd", "1", "variant"), ("none", "0", "variant"), ("none", "1", "variant"),
        ("teacher", "0", "upstream"), ("teacher", "1", "upstream")]
    by = {(r["variant"], r["seed"]): r for r in rows}
    assert all(r["selected_by"] == "val miou" and r["split"] == "test" and int(r["threads"]) >= 1 for r in rows)
    md = (root / "results.md").read_text()
    assert "| DSKD | dskd×10 | 0,1 |" in md and "Δ 95 % interval" in md and "best validation mIoU" in md
    delta = 100 * (float(by["dskd", "0"]["best_miou"]) - float(by["none", "0"]["best_miou"]))
    assert f"{delta:+.2f} / " in md  # the paired difference of seed 0, from the per-run scores
    assert (root / "results.png").stat().st_size > 0
    # started again: everything is reused, nothing is written again
    assert main(["sweep", str(path), "-o", str(out), "-q"]) == 0
    assert summaries(root) == runs


def test_a_shared_teacher_is_trained_once_and_an_interrupted_sweep_resumes(tmp_path: Path) -> None:
    path = write_sweep(tmp_path, upstream="shared", seeds=[3, 4])
    out = tmp_path / "runs"
    sweep = SweepRun(path, out, quiet=True)
    assert len(sweep.upstream_tasks()) == 1  # one teacher for both seeds
    sweep.pipes["dskd", 4].run(only=["dskd"], report=False)  # a sweep stopped after its first run
    before = summaries(out / "sw")
    sweep.run()
    after = summaries(out / "sw")
    assert {k: after[k] for k in before} == before and len(after) == 5  # resumed: the finished runs are kept
    teachers = list((out / "sw").glob("teacher-*/summary.json"))
    assert len(teachers) == 1 and yaml.safe_load((teachers[0].parent / "recipe.resolved.yaml").read_text())["seed"] == 0
    records, missing = sweep.records()
    assert not missing and len(records) == 5


def test_planned_commands_run_the_same_stages_and_sweep_then_only_collects(tmp_path: Path, capsys) -> None:
    path = write_sweep(tmp_path, seeds=[0])
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "--plan"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.strip().splitlines()
    assert lines[0].endswith("--stage teacher") and len(lines) == 3 and "run the first 1" in captured.err
    for line in lines:  # what each task of a cluster job array would run
        argv = shlex.split(line)
        assert argv[0] == "distilkit" and main(argv[1:] + ["-q"]) == 0
    sweep = SweepRun(path, out, quiet=True)
    for variant, recipe in sweep.sweep.recipes.items():  # the written recipes have the in-process identities
        assert Pipeline(load_recipe(sweep.recipe_file(variant)), out, seed=0).hashes == sweep.pipes[variant, 0].hashes
    runs = summaries(out / "sw")
    assert main(["sweep", str(path), "-o", str(out), "-q", "--collect"]) == 0
    assert summaries(out / "sw") == runs and (out / "sw" / "results.md").is_file()


@pytest.mark.parametrize("value", ["slurm", ["slurm"]])
def test_a_launcher_name_in_the_sweep_file_says_where_the_launcher_is_chosen(tmp_path: Path, capsys,
                                                                          value: object) -> None:
    from distilkit.sweep.spec import LauncherSpec

    path = write_sweep(tmp_path, launcher=value)
    assert main(["sweep", str(path), "-o", str(tmp_path / "runs"), "--plan"]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and not captured.out, err
    assert err.startswith(f"error: {path}: launcher: ") and "valid dictionary" not in err
    assert "chosen on the command line (`distilkit sweep FILE --launcher slurm`)" in err
    assert all(key in err for key in LauncherSpec.model_fields), err  # what the block holds
    assert not (tmp_path / "runs").exists()


def test_jobs_run_in_parallel_processes(tmp_path: Path, capsys) -> None:
    """`--jobs 2`: the runs go to `distilkit run` processes, each with its log; the output, not a terminal here (a
    file, a Slurm log), gets one line a finished run. Over 3 s: the child processes (each starts Python and torch,
    trains, writes its report) are its point."""
    path = write_sweep(tmp_path, seeds=[0])
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "--jobs", "2"]) == 0
    assert len(summaries(out / "sw")) == 3
    logs = sorted(p.name for p in (out / "sw" / "logs").iterdir())
    assert logs == ["dskd-seed0.log", "none-seed0.log", "teacher-seed0.log"]
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("[")]
    assert lines[0].startswith("[1/3] teacher (upstream of variant dskd), seed 0: finished in "), lines
    assert sorted(ln.split(": finished in ")[0][6:] for ln in lines[1:]) == ["dskd, seed 0", "none, seed 0"], lines
    assert [ln[:5] for ln in lines] == ["[1/3]", "[2/3]", "[3/3]"]  # counted in the order the runs end
    assert "2 left, about" in lines[0] and "all 3 done in" in lines[2]


def test_a_failed_run_is_said_in_its_line_and_the_others_go_on(tmp_path: Path, capsys) -> None:
    """A run whose loss overflows (KD x 1e39 in float32: an infinite loss, a clear error) fails; its line says
    so, the sweep still runs and tables the rest, and exits with status 2 naming it."""
    path = write_sweep(tmp_path, seeds=[0], variants={"none": {"distill": []},
                                                      "bad": {"distill": [{"name": "kd", "weight": 1e39}]}})
    out = tmp_path / "runs"
    code = main(["sweep", str(path), "-o", str(out), "--jobs", "2"])
    captured = capsys.readouterr()
    printed = captured.out
    lines = [ln for ln in printed.splitlines() if ln.startswith("[")]
    assert code == 2 and len(lines) == 3, printed
    assert "bad, seed 0: exit status" in captured.out + captured.err
    assert [ln for ln in lines if "bad, seed 0: failed in" in ln] and [ln for ln in lines if "none, seed 0: finished" in ln]
    assert (out / "sw" / "results.md").is_file()


def test_run_lines_say_what_is_left_at_the_pace_so_far() -> None:
    from distilkit.sweep.processes import RunLines

    lines = RunLines(4, console=None, enabled=False)
    lines.start -= 600  # two runs in 10 minutes (two jobs): 5 minutes a run, wall clock
    assert lines.done("kd, seed 0", 590) == "[1/4] kd, seed 0: finished in 10 min; 3 left, about 30 min more at this pace"
    assert lines.done("dist, seed 0", 3, failed=True) == \
        "[2/4] dist, seed 0: failed in 3 s; 2 left, about 10 min more at this pace"
    lines.start -= 3 * 3600
    lines.done("x", 1)
    assert lines.done("y", 1) == "[4/4] y: finished in 1 s; all 4 done in 3 h 10 min"


@pytest.mark.parametrize("change, message", [
    ({"variants": {"x": {"distil": []}}}, "variants.x.distil: unknown key"),
    ({"variants": {"x": {"set": {"stages.student.train.steps.deep": 1}}}},
     "variants.x.set: stages.student.train.steps.deep: stages.student.train.steps is a int"),
    ({"variants": {"kd": {"distill": [{"name": "kdd"}]}}}, "variants.kd"),
    ({"variants": {"x": {"set": {"stages.student.optimizer.lr": -1}}}}, "variants.x (recipe stages.student.optimizer.lr)"),
    ({"stage": "studnet"}, "no stage 'studnet'"),
    ({"baseline": "nothing"}, "baseline 'nothing' is not a variant"),
    ({"variants": {"teacher": {"distill": []}}}, "has the name of a stage"),
    ({"teacher": None, "variants": {"kd": {"distill": [{"name": "kd"}]}}}, "has no teacher"),
    ({"seeds": [1, 1]}, "give each seed once"),
])
def test_sweep_file_problems_are_named(tmp_path: Path, change: dict, message: str) -> None:
    path = write_sweep(tmp_path)
    data = yaml.safe_load(path.read_text())
    data.update(change)
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(RecipeError) as err:
        SweepRun(path, tmp_path / "runs", quiet=True)
    assert message in str(err.value) and str(path) in str(err.value)


@pytest.mark.parametrize(("name", "seeds"), [("quickstart_methods", 6), ("scpnet_table4", 6),
                                             ("scribble2scene_table5", 3), ("dskd_weight", 6), ("hassc", 6),
                                             ("l2cocc", 6)])
def test_shipped_sweeps_resolve(name: str, seeds: int, tmp_path: Path) -> None:
    sweep = SweepRun(ROOT / "recipes" / "sweeps" / f"{name}.yaml", tmp_path, quiet=True)
    assert sweep.sweep.baseline == "none" and len(sweep.variant_tasks()) == seeds * len(sweep.sweep.recipes)
    assert load_sweep(ROOT / "recipes" / "sweeps" / f"{name}.yaml").recipes["none"].stages["none"].teacher is None


def test_the_store_sweeps_keep_each_variants_store_and_the_stored_methods_sweep_is_the_readme_ones(tmp_path) -> None:
    """The sweep's teacher edge keeps what the sweep file and its variants say of the teacher (here the store and
    its layout): the stored quickstart methods are the README's methods, each reading a store; the layouts sweep
    compares each layout with the live teacher."""
    stored = load_sweep(ROOT / "recipes" / "sweeps" / "quickstart_methods_stored.yaml")
    live = load_sweep(ROOT / "recipes" / "sweeps" / "quickstart_methods.yaml")
    assert list(stored.recipes) == list(live.recipes) and stored.controls == live.controls
    assert {kind for _, kind in live.controls.values()} == {"random", "shuffled"}
    for name, recipe in stored.recipes.items():
        stage, twin = recipe.stages[name], live.recipes[name].stages[name]
        assert stage.distill == twin.distill
        if name == "none":
            assert stage.teacher is None
            continue
        assert stage.teacher.from_ == twin.teacher.from_ == "teacher" and stage.teacher.control == twin.teacher.control
        # a random teacher has no store to read (it is not the stored teacher): it runs live, as in the live sweep
        assert (stage.teacher.store is None) if stage.teacher.control == "random" else stage.teacher.store is not None
    layouts = load_sweep(ROOT / "recipes" / "sweeps" / "store_layouts.yaml").recipes
    got = {n: r.stages[n].teacher.store for n, r in layouts.items()}
    assert got["live"] is None and got["float32"].exact and got["bfloat16"].precision == "bfloat16"
    assert got["valid"].voxels == "valid" and got["topk4"].topk == 4


def test_the_scribble2scene_table_varies_the_camera_student_of_its_recipe(tmp_path: Path) -> None:
    """Table 5/6 compare methods on the camera student trained on the Dean-Labeler's labels, distilled from the
    frozen Teacher-Labeler; the Stage-I models are shared by every variant and seed."""
    sweep = SweepRun(ROOT / "recipes" / "sweeps" / "scribble2scene_table5.yaml", tmp_path, quiet=True)
    recipe = sweep.sweep.recipes["rgo2d"]
    stage = recipe.stages["rgo2d"]
    assert stage.model.adapter == "voxformer" and stage.labels.from_ == "dean" and stage.teacher.from_ == "teacher_labeler"
    assert {"no_global", "no_local", "no_range", "no_feature", "kd", "mgd", "dist", "cleaners"} <= set(sweep.sweep.recipes)
    # Table 6 removes one item at a time: every ablation but no_feature keeps the feature term (its taps)
    for name in ("no_global", "no_local", "no_range"):
        (term,) = sweep.sweep.recipes[name].stages[name].distill
        assert term.name == "rgo2d" and term.taps.get("student_features") == "image_features", name
        assert "feature_weight" not in term.params  # the default 0.6
    (no_feature,) = sweep.sweep.recipes["no_feature"].stages["no_feature"].distill
    assert "student_features" not in no_feature.taps
    # the CE of Scribble2Scene's released code: x10
    (ce,) = [t for t in recipe.stages["rgo2d"].task_losses if t.name == "weighted_ce"]
    assert ce.weight == 10
    teacher_dirs = {sweep.pipes[v, s].run_dir("teacher_labeler").name for v in sweep.sweep.recipes for s in sweep.seeds
                    if v != "none"}
    assert len(teacher_dirs) == 1


def test_the_hassc_sweep_keeps_its_own_ema_teacher_and_the_l2cocc_sweep_the_lidar_teacher(tmp_path: Path) -> None:
    """A variant that sets ``teacher: {ema: true}`` keeps it (the sweep's teacher edge is not forced on it) and needs
    no upstream teacher; HASSC's variant differs from the baseline only in what the file says."""
    hassc = SweepRun(ROOT / "recipes" / "sweeps" / "hassc.yaml", tmp_path, quiet=True).sweep
    full = hassc.recipes["hassc"].stages["hassc"]
    assert full.teacher.ema is not None and full.teacher.from_ is None and full.labels.from_ == "dean"
    assert [t.name for t in full.distill] == ["hassc_kd", "hassc_hvm"]
    assert [(t.name, t.weight) for t in full.task_losses] == [("hassc_ce", 10), ("geo_scal", None)]
    assert "teacher_labeler" not in hassc.upstream_stages("hassc")
    assert hassc.recipes["ema_kd"].stages["ema_kd"].teacher.ema is not None
    base = hassc.recipes["none"].stages["none"]
    assert base.teacher is None and [t.name for t in base.task_losses] == ["weighted_ce", "geo_scal"]
    l2 = SweepRun(ROOT / "recipes" / "sweeps" / "l2cocc.yaml", tmp_path, quiet=True).sweep
    stage = l2.recipes["pad_fsd"].stages["pad_fsd"]
    assert stage.teacher.from_ == "lidar_teacher" and "bottleneck" in stage.teacher.taps
    assert [(t.name, t.connector) for t in stage.distill] == [("l2cocc_pad", None), ("l2cocc_fsd", "linear")]


@pytest.mark.parametrize("name", ["scpnet_table4"])
def test_the_paper_tables_are_the_same_runs_as_the_readme_comparison(name: str, tmp_path: Path) -> None:
    """Their comments say so: each variant has the identity (configuration hash) of the README's variant with the
    same objectives, at every seed, so the numbers are the README's."""
    readme = SweepRun(ROOT / "recipes" / "sweeps" / "quickstart_methods_stored.yaml", tmp_path, quiet=True)
    table = SweepRun(ROOT / "recipes" / "sweeps" / f"{name}.yaml", tmp_path, quiet=True)

    def objectives(sweep: SweepRun, variant: str) -> tuple:  # the terms, and the control teacher of a control row
        return ([(t.name, t.weight) for t in sweep.sweep.recipes[variant].stages[variant].distill],
                sweep.sweep.controls.get(variant, (None, None))[1])

    for variant in table.sweep.recipes:
        (twin,) = [v for v in readme.sweep.recipes if objectives(readme, v) == objectives(table, variant)]
        for seed in table.seeds:
            mine = table.pipes[variant, seed].run_dir(variant).name.rsplit("-", 1)[1]
            theirs = readme.pipes[twin, seed].run_dir(twin).name.rsplit("-", 1)[1]
            assert mine == theirs, (variant, twin, seed)


def _record(name: str, seed: int, miou: float, upstream: bool = False, metric: str = "ssc"):
    from distilkit.sweep.results import RunRecord

    scores = {"miou": miou, "iou": 0.5} if metric == "ssc" else {"iou": miou, "precision": 0.8, "recall": 0.7}
    key = "miou" if metric == "ssc" else "iou"
    summary = {"stage": name, "label": name, "adapter": "voxformer", "objectives": [], "input": "1 frame",
               "metric": {"name": metric, "key": key}, "report_split": "test",
               "test": {"best": scores, "last": scores, "best_step": 5}, "best": {"step": 5, "scores": scores}}
    return RunRecord(name, seed, Path(f"/runs/{name}-{seed}"), summary, upstream)


def test_upstream_rows_get_no_difference_and_one_scored_by_another_metric_is_a_note_not_a_row() -> None:
    """The table's columns are the variants' metric: an upstream query-proposal stage (occupancy IoU, precision)
    would put its IoU under 'mIoU'; a labeler scored like the variants keeps its row, without a Δ to the baseline."""
    from distilkit.sweep.results import sweep_rows

    records = [_record("none", s, 0.20 + 0.01 * s) for s in (0, 1)] + \
              [_record("kd", s, 0.25 + 0.02 * s) for s in (0, 1)] + \
              [_record("labeler", 0, 0.5, upstream=True), _record("proposal", 0, 0.66, upstream=True, metric="occupancy")]
    rows, notes = sweep_rows(records, "none", ["none", "kd", "proposal", "labeler"])
    by = {r["stage"]: r for r in rows}
    assert list(by) == ["none", "kd", "labeler"]
    assert by["kd"]["delta"] == pytest.approx([0.05, 0.06])  # the variants are compared
    assert by["labeler"]["delta"] == [] and by["labeler"]["label"] == "*labeler* (upstream)"
    assert by["labeler"]["main"] == [0.5]
    assert notes == ["Upstream *proposal* (seed 0) is scored by its own metric, not in the table: test IoU 66.00, "
                     "precision 80.00 (best validation IoU 66.00)."]


def test_the_runs_left_out_are_said_by_variant_and_seed_range() -> None:
    """A sweep under way misses hundreds of runs: said as groups of variants missing the same seeds."""
    from distilkit.sweep.tasks import missing_text, seeds_text

    assert [seeds_text(s) for s in ([3], [1, 2, 3, 4, 5], [0, 2, 3, 4, 7], [0, 1], [5, 4, 5])] == \
        ["seed 3", "seeds 1–5", "seeds 0, 2–4, 7", "seeds 0, 1", "seeds 4, 5"]
    every = ["none", "kd", "dist"]
    assert missing_text([(v, s) for v in every for s in (1, 2)], every) == ["every variant (seeds 1, 2)"]
    assert missing_text([("dist", 0), ("kd", 1), ("none", 1), ("dist", 1)], every) == \
        ["none, kd (seed 1)", "dist (seeds 0, 1)"]
    assert missing_text([], every) == []
