"""Runs that survive faults: one writer per output folder, and a truncated checkpoint replaced by the previous one."""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from typing import Iterator

import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import process_context, tiny_recipe
from distilkit.cli import main
from distilkit.weights import load_checkpoint
from distilkit.engine.store.lock import lock_path, stage_lock
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RunLockedError
from distilkit.recipe import recipe_from_dict


def test_a_second_run_on_a_stage_in_training_waits_for_it_or_stops_with_a_clear_message(tmp_path, capsys,
                                                                                        monkeypatch) -> None:
    """Another process's lock held: ``--no-wait`` stops with exit 2 and the holder named, nothing written; the
    default says it waits (its ``on_wait`` is called), is still waiting, and trains the stage once released."""
    import distilkit.engine.store.lock as locks

    recipe = tiny_recipe(steps=1, distill=False)
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    lock = lock_path(pipe.root, pipe.run_dir("teacher").name)
    told = threading.Event()  # the waiter found the lock taken and began waiting: no fixed sleep needed

    def telling_lock(path, wait=True, on_wait=None, **kwargs):
        def tell(holder: str) -> None:
            told.set()
            if on_wait is not None:
                on_wait(holder)
        return stage_lock(path, wait=wait, on_wait=tell, **kwargs)

    monkeypatch.setattr(locks, "stage_lock", telling_lock)  # the pipeline imports it from there when it runs
    with stage_lock(lock):  # another process's lock: flock conflicts across open file descriptions
        with pytest.raises(RunLockedError, match=r"teacher-\w+ is being trained by another distilkit run \(pid \d+"):
            pipe.run(wait=False)
        assert main(["run", str(path), "-o", str(tmp_path / "runs"), "-q", "--no-wait"]) == 2
        assert "is being trained by another distilkit run" in capsys.readouterr().err
        assert not any(pipe.root.glob("teacher-*/summary.json"))  # nothing was written under the holder's feet
        assert not told.is_set()  # --no-wait never waited
        waited: list[str] = []

        def run_waiting() -> None:
            waited.extend(r.summary["status"] for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs",
                                                                quiet=True).run())

        waiter = threading.Thread(target=run_waiting)
        waiter.start()
        assert told.wait(timeout=120)
        waiter.join(timeout=0.2)
        assert waiter.is_alive() and not waited  # the default waits for the holder
        assert not any(pipe.root.glob("teacher-*/summary.json"))
    waiter.join(timeout=120)
    assert waited == ["finished"]  # released: it trained the stage


@pytest.mark.xdist_group("faults_clean_run")  # one worker trains the shared clean run once
def test_a_truncated_last_checkpoint_falls_back_to_the_previous_one_with_the_same_result(tmp_path, clean_run) -> None:
    """Stopped after step 3, ``last.pt`` cut short: the run resumes from ``last.prev.pt`` (step 2), logs why, and
    ends with the clean run's metrics (the shared 8-step run below)."""
    recipe = _kill_recipe()
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    pipe.run(stop_after=3)
    ckpts = pipe.run_dir("teacher") / "checkpoints"
    assert load_checkpoint(ckpts / "last.prev.pt")["step"] == 2
    last = ckpts / "last.pt"
    last.write_bytes(last.read_bytes()[:100])  # a crash mid-copy, a full disk: unreadable
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    log = [json.loads(x) for x in (pipe.run_dir("teacher") / "metrics.jsonl").read_text().splitlines()]
    bad = [r for r in log if r.get("event") == "unreadable_checkpoint"]
    assert bad and bad[0]["path"].endswith("last.pt") and "not a readable checkpoint" in bad[0]["error"]
    assert [r["step"] for r in log if r.get("event") == "resume"] == [2]
    assert scores(result.summary) == scores(clean_run.summary)  # the same final metrics as an uninterrupted run


def scores(summary: dict) -> dict:
    """A summary's test scores, everything but the forward timing."""
    return {k: ({m: v for m, v in x.items() if m != "seconds_per_sample"} if isinstance(x, dict) else x)
            for k, x in summary["test"].items()}


def _run_quietly(argv: list[str]) -> None:
    """``distilkit run ARGV`` in a child process (forked from this one where it can be), its output thrown away."""
    import os

    import torch

    torch.set_num_threads(1)  # as this process (one_thread); more in a forked child can hang GNU OpenMP
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.dup2(null, 2)
    sys.exit(main(argv))


def _kill_when(argv: list[str], ready, timeout: float = 120.0) -> None:
    """``distilkit run ARGV`` in a process of its own, SIGKILLed once ``ready()``. Forked from this process (it
    need not import Python's and distilkit's modules again, ~4 s of CPU; spawned on a machine with a GPU, where a
    forked child cannot train: conftest.can_fork), with this process's one thread: reductions split over another
    number of threads round differently."""
    import os

    proc = process_context().Process(target=_run_quietly, args=(argv,))
    proc.start()
    try:
        t0 = time.monotonic()
        while not ready() and proc.is_alive() and time.monotonic() - t0 < timeout:
            time.sleep(0.005)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.join()


@pytest.fixture(autouse=True, scope="module")
def one_thread() -> Iterator[None]:
    """One thread for the module's runs, the clean one, the killed ones and the resumed ones alike (as under
    xdist): a child forked from a process whose GNU OpenMP ran on more threads hangs at its first parallel region."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _kill_recipe() -> dict:
    recipe = tiny_recipe(steps=8, distill=False)
    recipe["stages"]["teacher"]["train"]["eval_every"] = 4
    return recipe


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory: pytest.TempPathFactory):
    """The uninterrupted run every killed one must end equal to (trained once for all kill moments)."""
    (clean,) = Pipeline(recipe_from_dict(_kill_recipe()), tmp_path_factory.mktemp("clean"), quiet=True).run()
    return clean


@pytest.mark.xdist_group("faults_clean_run")
@pytest.mark.parametrize("moment", ["first checkpoint", pytest.param("best checkpoint", marks=pytest.mark.slow),
                                    pytest.param("sixth log line", marks=pytest.mark.slow), "evaluation",
                                    "mid-epoch, 2 loader workers"])
def test_a_run_killed_at_any_moment_resumes_to_the_same_final_metrics(tmp_path, moment: str, clean_run) -> None:
    """Three kill moments by default, all five in the slow run. Epochs are 2 steps long: a kill after the third
    step is in the middle of the second epoch (with 2 loader processes reading ahead; workers are not part of the
    stage's identity, so the clean run is the same stage). Over 3 s: the killed `distilkit run` process (forked from
    this one, and its loader processes in the mid-epoch case) is its point."""
    recipe = _kill_recipe()
    if moment.startswith("mid-epoch"):
        recipe["stages"]["teacher"]["train"]["workers"] = 2
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    clean = clean_run
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    run_dir = pipe.run_dir("teacher")
    ready = {"first checkpoint": lambda: (run_dir / "checkpoints" / "last.pt").is_file(),
             "best checkpoint": lambda: (run_dir / "checkpoints" / "best.pt").is_file(),
             "sixth log line": lambda: (run_dir / "metrics.jsonl").is_file()
             and (run_dir / "metrics.jsonl").read_text().count("\n") >= 6,
             "evaluation": lambda: any(run_dir.glob("**/.*")),  # a temporary file: a write under way
             "mid-epoch, 2 loader workers": lambda: (run_dir / "metrics.jsonl").is_file()
             and '"step": 3' in (run_dir / "metrics.jsonl").read_text()}[moment]
    _kill_when(["run", str(path), "-o", str(tmp_path / "runs"), "-q"], ready)
    if moment != "evaluation":  # killed mid-run (the last moment may race with the end of the run)
        assert not (run_dir / "summary.json").is_file()
    assert not (run_dir / "summary.json").is_file() or json.loads((run_dir / "summary.json").read_text())
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert scores(result.summary) == scores(clean.summary)
    assert not [p.name for p in run_dir.glob("**/.*")]  # no temporary file of the killed writer is left
    for name in ("last.pt", "best.pt"):
        assert load_checkpoint(run_dir / "checkpoints" / name)["step"] in (4, 8)
