"""Experiment trackers with the real libraries, offline: the quickstart recipe (cut to a few steps on tiny scenes) run
with ``--set 'trackers=[tensorboard, {wandb: {mode: offline}}, mlflow, trackio]'``, stopped after two steps and
resumed; each tracker's run, read back with the library's own files or client, holds the TensorBoard events'
keys, steps and values, the identity and the final scores, and is one run across the two commands (run in the
test's process: what a resume carries over is on disk; a fresh process is kept where it is the point). No test logs
in anywhere: W&B runs offline, MLflow writes a SQLite file, Trackio its local folder."""

from __future__ import annotations

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
        for extra in (["--stop-after", "1"], []):
            assert main([*argv, *extra]) == 0
        import trackio.context_vars
        import trackio.utils

        trackio_dir = Path(trackio.utils.TRACKIO_DIR)
        trackio.context_vars.current_run.set(None)  # finished already: not again at this process's exit (a print)
    runs = {p.name.split("-")[0]: p for p in (tmp / "runs" / "quickstart").iterdir() if (p / "summary.json").is_file()}
    return {"tmp": tmp, "runs": runs, "trackio_dir": trackio_dir}


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
              for k in run.data.metrics if k.startswith(("train/", "val/"))}
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
            if key.startswith(("train/", "val/")):
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
