"""Experiment trackers with the real libraries, offline: the quickstart recipe (cut to a few steps on tiny scenes) run
with ``--set 'trackers=[tensorboard, {wandb: {mode: offline}}, mlflow, trackio]'``, stopped after two steps and
resumed; each tracker's run, read back with the library's own files or client, holds the TensorBoard events'
keys, steps and values, the identity and the final scores, and is one run across the two commands (run in the
test's process: what a resume carries over is on disk; a fresh process is kept where it is the point). No test logs
in anywhere: W&B runs offline, MLflow writes a SQLite file, Trackio its local folder."""

from __future__ import annotations

import contextlib
import io
import json
import os
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from conftest import TINY_DATA, tiny_recipe
from distilkit.errors import RecipeError

ROOT = Path(__file__).resolve().parents[1]
TRACKERS = "trackers=[tensorboard, {wandb: {mode: offline, project: from-recipe}}, mlflow, trackio]"
SMALL = [f"data.params.{k}={v}" for k, v in {**TINY_DATA, "input_frames": 4, "gt_frames": 4}.items()] + [
    "stages.*.model.params.channels=4", "stages.*.model.params.point_mlp=[8]", "stages.*.model.params.seg_channels=4",
    "stages.*.train.steps=2", "stages.*.train.eval_every=1", "stages.*.train.log_every=1",
    "stages.*.train.batch_size=1", "stages.*.train.device=cpu"]
LIBRARIES = ("wandb", "mlflow", "trackio")


def clean_env(tmp: Path, **extra: str) -> dict[str, str]:
    """This environment without any tracker's variables (no key, no mode), the stores in ``tmp``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("WANDB_", "MLFLOW_", "TRACKIO_", "DISTILKIT_SW"))}
    return {**env, "TRACKIO_DIR": str(tmp / "trackio"), "MLFLOW_TRACKING_URI": mlflow_store(tmp),
            "MLFLOW_ALLOW_FILE_STORE": "true", "HF_HUB_OFFLINE": "1", "WANDB_SILENT": "true", **extra}


def mlflow_store(tmp: Path) -> str:
    """A local MLflow file store (MLflow 3 asks for MLFLOW_ALLOW_FILE_STORE; its SQLite store takes ~15 s to create
    its tables on a loaded 2-core machine, the file store none)."""
    return (tmp / "mlruns").as_uri()


@pytest.fixture(scope="module")
def tracked(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """``distilkit run recipes/quickstart.yaml --stage student_dist`` (teacher and DIST student) with every tracker:
    stopped after 1 of the teacher's 2 steps, then run to the end by a second ``distilkit run``. Both run in this
    process (``main``): what the second carries over from the first is on disk (``trackers.json``, the checkpoints),
    and each ends its trackers' runs, as a process would. W&B's project and MLflow's experiment come from their
    environment variables, which win over the recipe. Trackio reads ``TRACKIO_DIR`` when imported: imported here
    first (no other test module imports it), its folder is read back from Trackio itself."""
    from distilkit.cli import main

    tmp = tmp_path_factory.mktemp("tracked")
    argv = ["run", str(ROOT / "recipes" / "quickstart.yaml"), "-o", str(tmp / "runs"), "-q", "--stage",
            "student_dist", "--set", TRACKERS, *SMALL]
    with pytest.MonkeyPatch.context() as patch:
        for key in [k for k in os.environ if k.startswith(("WANDB_", "MLFLOW_", "TRACKIO_", "DISTILKIT_SW"))]:
            patch.delenv(key)
        for key, value in clean_env(tmp, WANDB_PROJECT="from-env", MLFLOW_EXPERIMENT_NAME="kd-env").items():
            if os.environ.get(key) != value:
                patch.setenv(key, value)
        patch.chdir(tmp)
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
            for extra in (["--stop-after", "1"], []):
                assert main([*argv, *extra]) == 0
        import trackio.context_vars
        import trackio.utils

        trackio_dir = Path(trackio.utils.TRACKIO_DIR)
        left = trackio.context_vars.current_run.get()  # Trackio finishes it (a print) when the process exits
        trackio.context_vars.current_run.set(None)
    runs = {p.name.split("-")[0]: p for p in (tmp / "runs" / "quickstart").iterdir() if (p / "summary.json").is_file()}
    return {"tmp": tmp, "runs": runs, "trackio_dir": trackio_dir, "printed": printed.getvalue(), "left": left}


def tensorboard_scalars(run_dir: Path) -> dict[str, dict[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run_dir / "tensorboard"))
    events.Reload()
    return {tag: {e.step: e.value for e in events.Scalars(tag)} for tag in events.Tags()["scalars"]}


def wandb_records(path: Path) -> list[Any]:
    """The records of a W&B offline run file (``run-<id>.wandb``): a ``:W&B`` header, then records in 32 KiB blocks,
    each chunk with a 7-byte header (checksum, length, type: full, first, middle, last) — LevelDB's log format."""
    from wandb.proto import wandb_internal_pb2 as pb

    data = path.read_bytes()
    assert data[:4] == b":W&B"
    pos, block, out, parts = 7, 32768, [], []
    while pos + 7 <= len(data):
        left = block - pos % block
        if left < 7:
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if length == 0 and kind == 0:  # the rest of a block
            pos += left
            continue
        parts.append(data[pos + 7:pos + 7 + length])
        pos += 7 + length
        if kind in (1, 4):
            record = pb.Record()
            record.ParseFromString(b"".join(parts))
            out.append(record)
            parts = []
    return out


def wandb_run(run_dir: Path) -> dict[str, Any]:
    """Every offline folder of a stage's W&B run: their run ids, the logged history, the run records, the summary
    and the files."""
    ids, history, runs, summary, files = set(), {}, [], {}, set()
    folders = sorted((run_dir / "wandb").glob("offline-run-*"))
    for folder in folders:
        for record in wandb_records(next(folder.glob("run-*.wandb"))):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                ids.add(record.run.run_id)
                runs.append(record.run)
            elif kind == "history":
                step = record.history.step.num
                for item in record.history.item:
                    key = item.key or "/".join(item.nested_key)
                    if not key.startswith("_"):
                        history.setdefault(key, {})[step] = json.loads(item.value_json)
            elif kind == "summary":
                summary.update({i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in record.summary.update})
        files |= {p.name for p in (folder / "files").iterdir()}
    return {"folders": folders, "ids": ids, "history": history, "runs": runs, "summary": summary, "files": files}


def assert_same_scalars(logged: dict[str, dict[int, float]], events: dict[str, dict[int, float]]) -> None:
    """The keys, steps and values TensorBoard has (its events hold float32)."""
    assert set(logged) == set(events)
    for key, by_step in events.items():
        assert logged[key] == pytest.approx(by_step, rel=1e-6, abs=1e-7), key


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
def test_tensorboard_gets_every_term_the_task_loss_the_rate_and_the_scores(tracked) -> None:
    events = tensorboard_scalars(tracked["runs"]["student_dist"])
    # the total, the weighted DIST term, the task loss's terms, the learning rate; the validation scores
    assert {"train/loss", "train/kd_dist", "train/ce", "train/lovasz", "train/lr", "val/miou", "val/iou"} <= set(events)
    logged = [json.loads(line) for line in (tracked["runs"]["student_dist"] / "metrics.jsonl").read_text().splitlines()]
    assert events["train/kd_dist"] == pytest.approx({r["step"]: r["kd_dist"] for r in logged if "kd_dist" in r},
                                                    rel=1e-6)
    assert sorted(events["val/miou"]) == [1, 2] and sorted(events["train/loss"]) == [1, 2]


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
def test_every_tracker_gets_the_per_class_scores_and_the_timing_apart_from_the_scores(tracked) -> None:
    """``class_iou`` (one IoU a class, the empty class left out) as ``val/class_iou/<class>``; the evaluation's
    ``seconds_per_sample`` as ``time/val_seconds_per_sample``, not among the scores; the final values alike."""
    from mlflow import MlflowClient

    run_dir = tracked["runs"]["student_dist"]
    summary = json.loads((run_dir / "summary.json").read_text())
    classes = summary["classes"]["names"][1:]
    events = tensorboard_scalars(run_dir)
    assert {f"val/class_iou/{c}" for c in classes} <= set(events) and "time/val_seconds_per_sample" in events
    assert not {k for k in events if k.endswith("seconds_per_sample") and not k.startswith("time/")}
    evaluation = [json.loads(line)["eval"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()
                  if '"eval"' in line][-1]
    assert events[f"val/class_iou/{classes[0]}"][2] == pytest.approx(evaluation["class_iou"][0], rel=1e-6)
    client = MlflowClient(tracking_uri=mlflow_store(tracked["tmp"]))
    run_id = json.loads((run_dir / "trackers.json").read_text())["mlflow"]["run_id"]
    final = client.get_run(run_id).data.metrics
    assert final[f"test/best/class_iou/{classes[-1]}"] == pytest.approx(summary["test"]["best"]["class_iou"][-1])
    assert "time/test_best_seconds_per_sample" in final and "test/best/seconds_per_sample" not in final


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
def test_trackio_and_mlflow_print_nothing_under_quiet(tracked) -> None:
    """Nothing of theirs in a ``-q`` run's output, and no Trackio run left for its exit handler to print about."""
    assert tracked["printed"] == "" and tracked["left"] is None


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
@pytest.mark.parametrize("stage", ["teacher", "student_dist"])
def test_wandb_offline_logs_what_tensorboard_logs_in_one_run(tracked, stage: str) -> None:
    run_dir = tracked["runs"][stage]
    got = wandb_run(run_dir)
    assert_same_scalars(got["history"], tensorboard_scalars(run_dir))
    kept = json.loads((run_dir / "trackers.json").read_text())["wandb"]
    assert got["ids"] == {kept}  # the teacher's two processes wrote one run (wandb sync joins its folders)
    assert len(got["folders"]) == (2 if stage == "teacher" else 1)
    record = got["runs"][-1]
    assert record.project == "from-env" and record.run_group == "quickstart" and record.job_type == stage
    config = {i.key: json.loads(i.value_json) for i in record.config.update}
    assert config["distilkit"]["stage"] == stage and config["stage"] == stage and config["seed"] == 0
    summary = json.loads((run_dir / "summary.json").read_text())
    assert got["summary"]["test/best/miou"] == pytest.approx(summary["test"]["best"]["miou"])
    assert {"report.md", "loss.png", "summary.json", "recipe.resolved.yaml"} <= got["files"]


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
@pytest.mark.parametrize("stage", ["teacher", "student_dist"])
def test_mlflow_logs_what_tensorboard_logs_in_one_run(tracked, stage: str, monkeypatch) -> None:
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    run_dir = tracked["runs"][stage]
    client = MlflowClient(tracking_uri=mlflow_store(tracked["tmp"]))
    experiment = client.get_experiment_by_name("kd-env")
    runs = client.search_runs([experiment.experiment_id], filter_string=f"tags.`distilkit.stage` = '{stage}'")
    assert len(runs) == 1  # the resumed teacher continued its run
    run = runs[0]
    assert run.info.run_id == json.loads((run_dir / "trackers.json").read_text())["mlflow"]["run_id"]
    assert run.info.status == "FINISHED" and run.data.params["distilkit/hash"] == run_dir.name.split("-")[-1]
    events = tensorboard_scalars(run_dir)
    logged = {k: {m.step: m.value for m in client.get_metric_history(run.info.run_id, k)}
              for k in run.data.metrics if k.startswith(("train/", "val/", "time/val_"))}
    assert_same_scalars(logged, events)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert run.data.metrics["test/best/miou"] == pytest.approx(summary["test"]["best"]["miou"])
    assert {"report.md", "loss.png", "summary.json"} <= {a.path for a in client.list_artifacts(run.info.run_id)}


@pytest.mark.xdist_group("trackers")  # one worker runs the module's shared run
@pytest.mark.parametrize("stage", ["teacher", "student_dist"])
def test_trackio_logs_what_tensorboard_logs_in_one_run(tracked, stage: str) -> None:
    run_dir = tracked["runs"][stage]
    from trackio.sqlite_storage import SQLiteStorage

    assert tracked["trackio_dir"] == tracked["tmp"] / "trackio"  # Trackio's files where TRACKIO_DIR said
    got = {"runs": SQLiteStorage.get_runs("quickstart"), "logs": SQLiteStorage.get_logs("quickstart", run_dir.name),
           "config": SQLiteStorage.get_run_config("quickstart", run_dir.name)}  # from its SQLite files
    assert got["runs"].count(run_dir.name) == 1
    logged: dict[str, dict[int, float]] = {}
    for row in got["logs"]:
        for key, value in row.items():
            if key.startswith(("train/", "val/", "time/val_")):
                logged.setdefault(key, {})[row["step"]] = value
    assert_same_scalars(logged, tensorboard_scalars(run_dir))
    final = [row for row in got["logs"] if "test/best/miou" in row]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert [row["test/best/miou"] for row in final] == pytest.approx([summary["test"]["best"]["miou"]])
    assert got["config"]["distilkit"]["stage"] == stage and got["config"]["_Group"] == "quickstart"


def test_without_trackers_no_tracker_library_is_imported(tmp_path: Path) -> None:
    """Importing distilkit, listing its hooks and running a recipe without trackers import none of them. A fresh
    process (what a test's process has imported is not a user's), its smallest run: a teacher's one step, the run
    report's figures built and closed unrendered (as conftest does in-process)."""
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(tiny_recipe(steps=1, distill=False)))
    code = ("import sys; import distilkit; from distilkit.cli import main; import distilkit.report.plots as plots\n"
            "def save(fig, path):\n    import matplotlib.pyplot as plt; plt.close(fig); path.write_bytes(b''); "
            "return path\nplots.save = save\n"
            f"assert main(['list', 'hooks']) == 0; assert main(['run', {str(path)!r}, '-o', {str(tmp_path)!r}, '-q']) == 0;"
            f" print(sorted(m for m in sys.modules if m.split('.')[0] in {LIBRARIES!r}))")
    done = subprocess.run([sys.executable, "-c", code], env=clean_env(tmp_path), capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert any((tmp_path / "tiny").glob("teacher-*/summary.json"))


def test_a_missing_library_is_a_problem_naming_its_pip_install_line(tmp_path: Path, monkeypatch) -> None:
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    recipe = {**tiny_recipe(steps=1, distill=False), "trackers": ["tensorboard", {"wandb": {"mode": "offline"}}]}
    monkeypatch.setitem(sys.modules, "wandb", None)  # as if not installed
    with pytest.raises(RecipeError, match=r"trackers\[1\]: the wandb tracker needs the wandb package, which is not "
                                          r"installed; pip install 'distilkit\[wandb\]'"):
        Pipeline(recipe_from_dict(recipe), tmp_path, quiet=True)
    recipe["trackers"] = [{"mlflow": {"tracking_uri": "x", "experimnt": "y"}}, "trackoi"]
    with pytest.raises(RecipeError) as err:
        Pipeline(recipe_from_dict(recipe), tmp_path, quiet=True)
    text = str(err.value)
    assert "trackers[0].params" in text and "experimnt" in text
    assert "trackers[1].name: unknown hook 'trackoi'; did you mean 'trackio'" in text
    with pytest.raises(RecipeError, match=r"trackers\[0\]: give one tracker per entry"):
        recipe_from_dict({**recipe, "trackers": [{"wandb": {}, "mlflow": {}}]})


def test_trackers_are_not_part_of_a_stage_identity(tmp_path: Path) -> None:
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    plain = Pipeline(recipe_from_dict(tiny_recipe(steps=1)), tmp_path, quiet=True)
    tracked = Pipeline(recipe_from_dict({**tiny_recipe(steps=1), "trackers": ["tensorboard"]}), tmp_path, quiet=True)
    assert plain.hashes == tracked.hashes
    assert [h.name for h in tracked.resolved.stages["student"].hooks] == ["tensorboard"]


def test_only_the_main_process_starts_a_tracker_run(tmp_path: Path, monkeypatch) -> None:
    from types import SimpleNamespace

    from distilkit.engine.hooks import Loop
    from distilkit.engine.train.trackers.to_mlflow import MlflowParams, MlflowTracker

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    (tmp_path / "recipe.resolved.yaml").write_text("recipe: r\nstage: s\nhash: h\nseed: 0\n")
    tracker = MlflowTracker(MlflowParams(tracking_uri=mlflow_store(tmp_path)))
    loop = Loop("s", tmp_path, SimpleNamespace(log_every=1), total=2, steps_per_epoch=2, eval_every=2, main=False,
                hooks=[tracker])
    for event in ("before_train", "after_step", "after_train"):
        loop.step += event == "after_step"
        loop.emit(event)
    loop.published({"test": {"best": {"miou": 1.0}}})
    assert not tracker.active and tracker.client is None
    assert not (tmp_path / "trackers.json").exists() and not (tmp_path / "mlruns").exists()


@pytest.mark.parametrize("jobs", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_a_sweep_logged_to_mlflow_nests_every_variant_and_seed_under_one_parent(tmp_path: Path, monkeypatch,
                                                                                  jobs: int) -> None:
    """In this process (``--jobs 1``) and in two processes at once (the sweep's environment handed to them, the
    parent run made once under the sweep's lock)."""
    from mlflow import MlflowClient

    from distilkit.cli import main
    from distilkit.engine.train.trackers.base import SWEEP_ENV

    base = tiny_recipe(steps=1)
    base["stages"]["student"].pop("distill")
    base["stages"]["student"].pop("teacher")
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(base))
    sweep = {"schema_version": 1, "name": "sw", "recipe": "base.yaml", "stage": "student", "teacher": "teacher",
             "seeds": [0, 1], "upstream": "shared", "set": {"trackers": ["mlflow"]},
             "variants": {"none": {"distill": []}, "dskd": {"distill": [{"name": "dskd", "weight": 10}]}}}
    (tmp_path / "sweep.yaml").write_text(yaml.safe_dump(sweep, sort_keys=False))
    uri = mlflow_store(tmp_path)
    for key in [k for k in os.environ if k.startswith(("MLFLOW_", "DISTILKIT_SW"))]:
        monkeypatch.delenv(key)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    assert main(["sweep", str(tmp_path / "sweep.yaml"), "-o", str(tmp_path / "runs"), "-q", "--jobs", str(jobs)]) == 0
    assert SWEEP_ENV not in os.environ  # restored after the sweep's runs
    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("sw")  # the sweep's name (its recipes are named after it)
    runs = client.search_runs([experiment.experiment_id])
    parents = [r for r in runs if r.data.tags.get("distilkit.role") == "sweep"]
    assert len(parents) == 1 and parents[0].info.run_name == "sw" and parents[0].info.status == "FINISHED"
    nested = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parents[0].info.run_id]
    assert len(nested) == len(runs) - 1  # every run of the sweep, its teachers too
    variants = sorted((r.data.tags["distilkit.variant"], r.data.tags["distilkit.seed"]) for r in nested
                      if r.data.tags["distilkit.role"] == "variant")
    assert variants == [("dskd", "0"), ("dskd", "1"), ("none", "0"), ("none", "1")]
    assert [r.data.tags["distilkit.stage"] for r in nested if r.data.tags["distilkit.role"] == "upstream"] == [
        "teacher"]  # shared by every variant and seed
    assert {r.info.run_name for r in nested} >= {"dskd-seed0", "none-seed1"}
    report = Path(parents[0].data.tags["distilkit.sweep_report"])
    assert report == (tmp_path / "runs" / "sw" / "results.md").resolve() and report.is_file()


# -- the paths after the first clean run: a resume after a kill, a failure, a signal, another folder ---------------

def stage_recipe(tmp: Path, name: str, trackers: list, steps: int = 6, eval_every: int = 4,
                 checkpoint_every: int = 2, distill: bool = False) -> Path:
    """The tiny teacher (and ``distill``: its student) logging every step, evaluated every ``eval_every`` steps,
    ``last.pt`` every ``checkpoint_every``, with ``trackers``."""
    recipe = tiny_recipe(name=name, steps=steps, distill=distill)
    for stage in recipe["stages"].values():
        stage["train"].update(eval_every=eval_every, checkpoint_every=checkpoint_every, log_every=1)
    recipe["trackers"] = trackers
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return path


@pytest.fixture
def stores(tmp_path: Path, monkeypatch) -> Path:
    """Every tracker's store in ``tmp_path`` (Trackio's where this process first imported it: ``trackio_dir``),
    no tracker variable from the machine."""
    for key in [k for k in os.environ if k.startswith(("WANDB_", "MLFLOW_", "TRACKIO_", "DISTILKIT_SW"))]:
        monkeypatch.delenv(key)
    for key, value in clean_env(tmp_path).items():
        if os.environ.get(key) != value:
            monkeypatch.setenv(key, value)
    monkeypatch.chdir(tmp_path)
    return tmp_path


def trackio_dir() -> Path:
    import trackio.utils

    return Path(trackio.utils.TRACKIO_DIR)


def trackio_rows(project: str) -> list[tuple[str, str, int, dict[str, Any]]]:
    """Every metrics row of a Trackio project, as written: (run id, run name, step, values)."""
    import sqlite3

    from trackio.sqlite_storage import SQLiteStorage

    with sqlite3.connect(SQLiteStorage.get_project_db_path(project)) as db:
        rows = db.execute("SELECT run_id, run_name, step, metrics FROM metrics ORDER BY id").fetchall()
    return [(i, n, s, json.loads(m)) for i, n, s, m in rows]


def mlflow_steps(client: Any, run_id: str, key: str) -> list[int]:
    return sorted(m.step for m in client.get_metric_history(run_id, key))


def wandb_rows(run_dir: Path) -> list[tuple[int, dict[str, Any]]]:
    """Every history row of a stage's W&B offline folders, in the order ``wandb sync`` sends them."""
    rows = []
    for folder in sorted((run_dir / "wandb").glob("offline-run-*")):
        for record in wandb_records(next(folder.glob("run-*.wandb"))):
            if record.WhichOneof("record_type") == "history":
                rows.append((record.history.step.num, {i.key or "/".join(i.nested_key): json.loads(i.value_json)
                                                       for i in record.history.item}))
    return rows


def wandb_ending(folder: Path) -> tuple[int | None, bool]:
    """The exit code an offline W&B folder recorded, and whether the run was marked preempting."""
    records = wandb_records(next(folder.glob("run-*.wandb")))
    codes = [r.exit.exit_code for r in records if r.WhichOneof("record_type") == "exit"]
    return (codes[-1] if codes else None), any(r.WhichOneof("record_type") == "preempting" for r in records)


def kept_train(run_dir: Path, key: str = "loss") -> dict[int, float]:
    """``metrics.jsonl``'s training value ``key`` by step: the record of the run."""
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r[key] for r in records if key in r and "event" not in r}


ALL = ["tensorboard", {"wandb": {"mode": "offline"}}, "mlflow", "trackio"]


@pytest.mark.xdist_group("trackers")
def test_a_resume_after_a_kill_leaves_every_tracker_each_step_once_with_the_kept_values(stores: Path) -> None:
    """Stopped after step 5 (``last.pt`` at 4), as a SIGKILL leaves it for W&B offline (its service writes the
    records it buffered at the end only: the killed process's file is its 7-byte header), then resumed: each
    tracker holds every step 1-6 once, with ``metrics.jsonl``'s values; step 5 is not logged twice. The stopped
    run is recorded as stopped (MLflow KILLED, W&B preempting with a non-zero exit, a Trackio alert)."""
    from mlflow import MlflowClient

    from distilkit.cli import main

    recipe = stage_recipe(stores, "killed", ALL)
    argv = ["run", str(recipe), "-o", str(stores / "runs"), "-q"]
    assert main([*argv, "--stop-after", "5"]) == 0
    run_dir = next((stores / "runs" / "killed").glob("teacher-*"))
    ids = json.loads((run_dir / "trackers.json").read_text())
    client = MlflowClient(tracking_uri=mlflow_store(stores))
    assert client.get_run(ids["mlflow"]["run_id"]).info.status == "KILLED"
    (folder,) = (run_dir / "wandb").glob("offline-run-*")
    code, preempting = wandb_ending(folder)
    assert code != 0 and preempting
    from trackio.sqlite_storage import SQLiteStorage

    alerts = SQLiteStorage.get_alerts("killed", run_id=ids["trackio"]["id"])
    assert [a["level"] for a in alerts] == ["warn"] and "stopped" in alerts[0]["title"]
    wandb_file = next(folder.glob("run-*.wandb"))
    wandb_file.write_bytes(wandb_file.read_bytes()[:7])  # what a SIGKILL leaves of the offline run
    assert main(argv) == 0

    kept = kept_train(run_dir)
    assert sorted(kept) == [1, 2, 3, 4, 5, 6]
    events = tensorboard_scalars(run_dir)
    assert events["train/loss"] == pytest.approx(kept, rel=1e-6)
    assert mlflow_steps(client, ids["mlflow"]["run_id"], "train/loss") == [1, 2, 3, 4, 5, 6]
    assert {m.step: m.value for m in client.get_metric_history(ids["mlflow"]["run_id"], "train/loss")} == kept
    assert mlflow_steps(client, ids["mlflow"]["run_id"], "val/miou") == [4, 6]
    rows = wandb_rows(run_dir)
    assert sorted(s for s, v in rows if "train/loss" in v) == [1, 2, 3, 4, 5, 6]
    assert {s: v["train/loss"] for s, v in rows if "train/loss" in v} == kept
    assert sorted(s for s, v in rows if "val/miou" in v) == [4, 6]
    trackio = [(s, v) for i, _, s, v in trackio_rows("killed") if i == ids["trackio"]["id"]]
    assert sorted(s for s, v in trackio if "train/loss" in v) == [1, 2, 3, 4, 5, 6]
    assert {s: v["train/loss"] for s, v in trackio if "train/loss" in v} == kept
    assert sorted(s for s, v in trackio if "val/miou" in v) == [4, 6]


@pytest.mark.xdist_group("trackers")
@pytest.mark.parametrize("how", ["failure", "sigterm"])
def test_a_failed_or_signalled_stage_is_recorded_as_such(stores: Path, monkeypatch, how: str) -> None:
    """A non-finite loss at step 3 (``last.pt`` at 2): MLflow FAILED, W&B exit code 1, a Trackio error alert.
    SIGTERM during step 3 (the loop writes ``last.pt`` at 3 and stops): MLflow KILLED, W&B preempting and a
    non-zero exit, a Trackio warning alert. Each holds the steps a checkpoint covers."""
    from mlflow import MlflowClient

    from distilkit.cli import main
    from distilkit.engine.train import stop
    from distilkit.engine.train.trainer import Trainer
    from distilkit.errors import NonFiniteLossError

    if how == "failure":
        step = Trainer.train_step

        def failing(self, batch, done):
            if done == 2:
                raise NonFiniteLossError(f"stage 'teacher', step {done + 1}: loss term(s) ce became nan")
            return step(self, batch, done)

        monkeypatch.setattr(Trainer, "train_step", failing)
    else:
        asked = iter(range(100))
        monkeypatch.setattr(stop, "requested", lambda: next(asked) >= 2)  # SIGTERM's handler sets it, during step 3
    recipe = stage_recipe(stores, how, [{"wandb": {"mode": "offline"}}, "mlflow", "trackio"], steps=4)
    assert main(["run", str(recipe), "-o", str(stores / "runs"), "-q"]) == (2 if how == "failure" else 130)
    run_dir = next((stores / "runs" / how).glob("teacher-*"))
    ids = json.loads((run_dir / "trackers.json").read_text())
    client = MlflowClient(tracking_uri=mlflow_store(stores))
    run = client.get_run(ids["mlflow"]["run_id"])
    assert run.info.status == ("FAILED" if how == "failure" else "KILLED")
    logged = [1, 2] if how == "failure" else [1, 2, 3]
    assert mlflow_steps(client, ids["mlflow"]["run_id"], "train/loss") == logged
    (folder,) = (run_dir / "wandb").glob("offline-run-*")
    assert wandb_ending(folder) == (1, how == "sigterm")
    from trackio.sqlite_storage import SQLiteStorage

    alerts = SQLiteStorage.get_alerts(how, run_id=ids["trackio"]["id"])
    assert [a["level"] for a in alerts] == ["error" if how == "failure" else "warn"]
    if how == "failure":
        assert "ce became nan" in alerts[0]["text"] and "ce became nan" in run.data.tags["distilkit.ended"]


@pytest.mark.xdist_group("trackers")
def test_trackio_continues_its_own_run_by_id_never_another_folders_run_of_the_same_name(stores: Path) -> None:
    """``run -o C --stop-after 1``, ``run -o D``, ``run -o C``: the same recipe, so the same run name in one
    Trackio project; C's resume continues C's run (by the id kept in its trackers.json), D's run is D's alone."""
    from trackio.sqlite_storage import SQLiteStorage

    from distilkit.cli import main

    recipe = stage_recipe(stores, "twofolders", ["trackio"], steps=2, eval_every=2, checkpoint_every=1)
    for out, extra in (("C", ["--stop-after", "1"]), ("D", []), ("C", [])):
        assert main(["run", str(recipe), "-o", str(stores / out), "-q", *extra]) == 0
    rows = trackio_rows("twofolders")
    for out in ("C", "D"):
        run_dir = next((stores / out / "twofolders").glob("teacher-*"))
        kept = json.loads((run_dir / "trackers.json").read_text())["trackio"]
        assert kept["dir"] == str(trackio_dir().resolve())
        steps = [s for i, _, s, v in rows if i == kept["id"] and "train/loss" in v]
        assert steps == [1, 2], out
        config = SQLiteStorage.get_run_config("twofolders", run_id=kept["id"])
        assert config["distilkit"]["run_dir"] == str(run_dir.resolve()), out
    assert len({i for i, *_ in rows}) == 2 and len({n for _, n, *_ in rows}) == 1


@pytest.mark.xdist_group("trackers")
def test_a_resume_from_another_working_folder_or_store_continues_or_starts_anew_with_a_warning(
        stores: Path, monkeypatch, capsys) -> None:
    """MLflow's store given as a relative path (``MLFLOW_TRACKING_URI=mlruns``): the resume from another working
    folder continues the run in the store it was kept in (``trackers.json``), not in a new ``mlruns`` there.
    Trackio's run gone from its folder (another ``TRACKIO_DIR``'s run): the resumed stage logs to a run of that id
    here, with every step the stage kept. An MLflow run whose store is gone: a warning, and a new run in the
    current store with every step the stage kept."""
    from mlflow import MlflowClient

    from distilkit.cli import main
    from trackio.sqlite_storage import SQLiteStorage

    for folder in ("A", "B"):
        (stores / folder).mkdir()
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "mlruns")
    recipe = stage_recipe(stores, "elsewhere", ["mlflow", "trackio"], steps=3, eval_every=3, checkpoint_every=1)
    argv = ["run", str(recipe), "-o", str(stores / "runs"), "-q"]
    monkeypatch.chdir(stores / "A")
    assert main([*argv, "--stop-after", "2"]) == 0
    run_dir = next((stores / "runs" / "elsewhere").glob("teacher-*"))
    ids = json.loads((run_dir / "trackers.json").read_text())
    SQLiteStorage.get_project_db_path("elsewhere").unlink()  # Trackio's project is not in this TRACKIO_DIR
    monkeypatch.chdir(stores / "B")
    assert main(argv) == 0
    client = MlflowClient(tracking_uri=(stores / "A" / "mlruns").as_uri())
    assert client.get_run(ids["mlflow"]["run_id"]).info.status == "FINISHED"
    assert mlflow_steps(client, ids["mlflow"]["run_id"], "train/loss") == [1, 2, 3]
    assert not (stores / "B" / "mlruns").exists()
    assert sorted(s for i, _, s, v in trackio_rows("elsewhere") if i == ids["trackio"]["id"] and "train/loss" in v) \
        == [1, 2, 3]

    import shutil

    shutil.rmtree(run_dir)  # again, and the store the run was kept in is gone before the resume
    monkeypatch.chdir(stores / "A")
    assert main([*argv, "--stop-after", "2"]) == 0
    ids = json.loads((run_dir / "trackers.json").read_text())
    ids["mlflow"]["tracking_uri"] = (stores / "gone" / "mlruns").as_uri()
    (run_dir / "trackers.json").write_text(json.dumps(ids))
    capsys.readouterr()
    assert main(argv) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "mlflow" in line.lower()]
    assert len(warned) == 1 and "is not in" in warned[0] and "a new run" in warned[0], warned
    new = json.loads((run_dir / "trackers.json").read_text())["mlflow"]
    client = MlflowClient(tracking_uri=new["tracking_uri"])
    assert mlflow_steps(client, new["run_id"], "train/loss") == [1, 2, 3]


@pytest.mark.xdist_group("trackers")
def test_a_disabled_or_failing_tracker_warns_and_the_stages_go_on(stores: Path, monkeypatch, capsys) -> None:
    """W&B ``mode: disabled`` (and ``WANDB_MODE=disabled``) logs nothing and ends no stage in an error; a tracker
    whose library raises at the end of a stage is one warning line, and every stage finishes."""
    from distilkit.cli import main
    from distilkit.engine.train.trackers.to_mlflow import MlflowTracker

    def broken(self, paths):
        raise OSError(2, "No such file or directory", "report.md")

    monkeypatch.setattr(MlflowTracker, "files", broken)
    recipe = stage_recipe(stores, "disabled", ["tensorboard", {"wandb": {"mode": "disabled"}}, "mlflow"], steps=1,
                          eval_every=1, checkpoint_every=1, distill=True)
    capsys.readouterr()
    assert main(["run", str(recipe), "-o", str(stores / "runs"), "-q"]) == 0
    runs = sorted((stores / "runs" / "disabled").glob("*-*"))
    assert [p.name.split("-")[0] for p in runs if (p / "summary.json").is_file()] == ["student", "teacher"]
    warned = capsys.readouterr().err.splitlines()
    assert len(warned) == 2 and all("mlflow" in line and "report.md" in line for line in warned), warned
    for run_dir in runs:
        assert not (run_dir / "wandb").exists() and "wandb" not in json.loads((run_dir / "trackers.json").read_text())
        assert (run_dir / "tensorboard").is_dir()
        assert '"event": "warning"' in (run_dir / "metrics.jsonl").read_text()  # the record keeps it too
    monkeypatch.setenv("WANDB_MODE", "disabled")
    recipe = stage_recipe(stores, "disabled-env", [{"wandb": {"mode": "offline"}}], steps=1, eval_every=1,
                          checkpoint_every=1)
    assert main(["run", str(recipe), "-o", str(stores / "runs"), "-q"]) == 0
    assert not any((stores / "runs" / "disabled-env").glob("*/wandb"))


@pytest.mark.parametrize("moment", ["start", "scalars", "finish"])
def test_a_tracker_that_raises_at_any_moment_is_one_warning_line_and_the_loop_goes_on(tmp_path: Path,
                                                                                        moment: str) -> None:
    """Its library raising when the run starts or values are logged: one warning, the run finished as failed,
    nothing more logged; when it is finished: one warning. The loop's moments all return."""
    from types import SimpleNamespace

    from distilkit.engine.hooks import Loop
    from distilkit.engine.train.trackers.base import Tracker, TrackerParams

    (tmp_path / "recipe.resolved.yaml").write_text("recipe: r\nstage: s\nhash: h\nseed: 0\n")
    calls: list[Any] = []

    class Broken(Tracker):
        key = "broken"

        def call(self, what: Any) -> None:
            calls.append(what)
            if what == moment or (moment == "scalars" and isinstance(what, int)):
                raise RuntimeError("the server went away\n(a second line)")

        def start(self, identity, resume, step) -> None:
            self.call("start")

        def scalars(self, values, step) -> None:
            self.call(step)

        def finish(self, status, why="") -> None:
            self.call("finish")
            calls.append(status)

    warned: list[str] = []
    loop = Loop("s", tmp_path, SimpleNamespace(log_every=1), total=2, steps_per_epoch=2, eval_every=2, main=True,
                _warn=warned.append, hooks=[Broken(TrackerParams())])
    loop.emit("before_train")
    for _ in range(2):
        loop.step += 1
        loop.values = {"loss": 1.0}
        loop.save("last")
        loop.emit("after_step")
    loop.emit("after_train")
    loop.published({})
    assert len(warned) == 1 and warned[0].startswith("the broken tracker failed") and "\n" not in warned[0], warned
    assert "RuntimeError: the server went away" in warned[0]
    assert calls == {"start": ["start", "finish", "failed"], "scalars": ["start", 1, "finish", "failed"],
                     "finish": ["start", 1, 2, "finish"]}[moment]


KILLER = """import os, signal, sys
from distilkit.engine.train.trackers.base import Tracker, TrackerParams
from distilkit.registry import HOOKS

class KillAt(TrackerParams):
    step: int = 0

class Killer(Tracker):  # the last tracker: the others have seen the step
    def after_step(self, loop):
        if loop.main and loop.step == self.params.step:
            os.kill(os.getpid(), signal.SIGKILL)

HOOKS.add("kill-at", Killer, description="SIGKILL at a step", params=KillAt, tracker=True)
from distilkit.cli import main
sys.exit(main(sys.argv[1:]))
"""


def trackio_rows_elsewhere(project: str, env: dict[str, str]) -> list[tuple[str, int, str]]:
    """A Trackio project's metrics rows (run id, step, values as JSON) under ``env``'s ``TRACKIO_DIR``, read by a
    process of its own (Trackio reads the variable when it is imported)."""
    script = ("import json, sqlite3, sys; from trackio.sqlite_storage import SQLiteStorage as S\n"
              "db = sqlite3.connect(S.get_project_db_path(sys.argv[1]))\n"
              "rows = db.execute('SELECT run_id, step, metrics FROM metrics').fetchall()\n"
              "print(json.dumps([(i, s, bytes(m).decode()) for i, s, m in rows]))")
    done = subprocess.run([sys.executable, "-c", script, project], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


@pytest.mark.slow
def test_a_real_sigkill_and_a_resume_leave_every_tracker_each_step_once(tmp_path: Path, monkeypatch) -> None:
    """The issue's run: 12 steps, evaluated every 4, ``last.pt`` every 2, killed outright (SIGKILL) at step 7 in a
    process of its own, then ``distilkit run`` again (resumed from step 6): TensorBoard, W&B offline (the killed
    process's file holds none of its steps), MLflow and Trackio each hold steps 1-12 once, with the values in
    ``metrics.jsonl``; nothing is printed under ``-q``."""
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    recipe = stage_recipe(tmp_path, "sigkill", [*ALL, {"kill-at": {"step": 7}}], steps=12)
    env = clean_env(tmp_path)
    argv = ["run", str(recipe), "-o", str(tmp_path / "runs"), "-q"]
    killed = subprocess.run([sys.executable, "-c", KILLER, *argv], env=env, cwd=tmp_path, capture_output=True,
                            text=True, timeout=600)
    assert killed.returncode == -9, killed.stderr[-2000:]
    recipe.write_text(recipe.read_text().replace("- kill-at:\n    step: 7\n", ""))  # not part of the identity
    assert "kill-at" not in recipe.read_text()
    resumed = subprocess.run([sys.executable, "-m", "distilkit", *argv], env=env, cwd=tmp_path, capture_output=True,
                             text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert resumed.stdout == "" and resumed.stderr == ""
    run_dir = next((tmp_path / "runs" / "sigkill").glob("teacher-*"))
    kept = kept_train(run_dir)
    assert sorted(kept) == list(range(1, 13))
    ids = json.loads((run_dir / "trackers.json").read_text())
    assert tensorboard_scalars(run_dir)["train/loss"] == pytest.approx(kept, rel=1e-6)
    client = MlflowClient(tracking_uri=mlflow_store(tmp_path))
    history = client.get_metric_history(ids["mlflow"]["run_id"], "train/loss")
    assert sorted(m.step for m in history) == list(range(1, 13)) and {m.step: m.value for m in history} == kept
    assert mlflow_steps(client, ids["mlflow"]["run_id"], "val/miou") == [4, 8, 12]
    rows = wandb_rows(run_dir)
    assert sorted(s for s, v in rows if "train/loss" in v) == list(range(1, 13))
    assert {s: v["train/loss"] for s, v in rows if "train/loss" in v} == kept
    assert len(list((run_dir / "wandb").glob("offline-run-*"))) == 2
    rows = trackio_rows_elsewhere("sigkill", env)
    trackio = {}
    for run_id, step, values in rows:
        if run_id == ids["trackio"]["id"] and "train/loss" in json.loads(values):
            assert step not in trackio
            trackio[step] = json.loads(values)["train/loss"]
    assert trackio == kept


@pytest.mark.slow
def test_a_resume_with_another_trackio_dir_starts_a_new_run_there_with_a_warning(tmp_path: Path) -> None:
    """Trackio reads ``TRACKIO_DIR`` when it is imported: a stage stopped with one folder and resumed with another
    starts a new run in the second (one warning line, no traceback), holding every step once."""
    recipe = stage_recipe(tmp_path, "moved", ["trackio"], steps=3, eval_every=3, checkpoint_every=1)
    argv = [sys.executable, "-m", "distilkit", "run", str(recipe), "-o", str(tmp_path / "runs"), "-q"]
    first = subprocess.run([*argv, "--stop-after", "2"], env=clean_env(tmp_path), cwd=tmp_path, capture_output=True,
                           text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    env = clean_env(tmp_path, TRACKIO_DIR=str(tmp_path / "trackio-2"))
    done = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert len(done.stderr.splitlines()) == 1 and "a new run is started here" in done.stderr, done.stderr
    run_dir = next((tmp_path / "runs" / "moved").glob("teacher-*"))
    kept = json.loads((run_dir / "trackers.json").read_text())["trackio"]
    assert kept["dir"] == str((tmp_path / "trackio-2").resolve())
    rows = trackio_rows_elsewhere("moved", env)
    assert sorted(s for i, s, v in rows if i == kept["id"] and "train/loss" in json.loads(v)) == [1, 2, 3]
