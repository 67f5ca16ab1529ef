"""``distilkit sweep --launcher slurm`` on a real Slurm (slow): ``.ci/run`` starts a one-node Slurm with
``.ci/slurm-up`` (Debian's Slurm 22.05 and munge) and sets ``DISTILKIT_REQUIRE_SLURM=1``; elsewhere this test runs
where ``sinfo`` answers and skips, saying so, where it does not.

A 2-variant x 2-seed tiny sweep with a shared teacher is queued at once (``--cpus-per-run 1``); one student job is
sent SIGTERM mid-training (``scancel --signal=TERM --full``), requeues itself, resumes from its checkpoint; ``--wait``
follows the jobs and collects; the table and every run's weights equal the local launcher's (``--jobs 2``: one
thread a run there too) bit for bit."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from test_sweep import write_sweep

pytestmark = pytest.mark.slow


def slurm_or_skip() -> None:
    ok = shutil.which("sinfo") is not None and subprocess.run(["sinfo", "-h"], capture_output=True).returncode == 0
    if not ok:
        if os.environ.get("DISTILKIT_REQUIRE_SLURM") == "1":
            raise AssertionError("DISTILKIT_REQUIRE_SLURM=1 but no Slurm answers (sinfo); .ci/slurm-up starts one")
        pytest.skip("no Slurm here (sinfo does not answer); CI starts one with .ci/slurm-up")


def distilkit(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "distilkit", *argv], cwd=cwd, capture_output=True, text=True,
                          timeout=900)


def job_state(job: str) -> tuple[str, int]:
    out = subprocess.run(["scontrol", "show", "job", job], capture_output=True, text=True).stdout
    state = out.split("JobState=")[1].split()[0] if "JobState=" in out else "?"
    restarts = int(out.split("Restarts=")[1].split()[0]) if "Restarts=" in out else 0
    return state, restarts


def table(path: Path) -> list[dict[str, str]]:
    """The results' rows without what may differ between launchers (the wall-clock time, the folder)."""
    with open(path, newline="") as f:
        return [{k: v for k, v in row.items() if k not in ("train_seconds", "input_wait_seconds", "run_dir")} for row in csv.DictReader(f)]


def test_a_sweep_on_slurm_requeues_a_preempted_run_and_equals_the_local_launcher_bit_for_bit(tmp_path) -> None:
    slurm_or_skip()
    path = write_sweep(tmp_path, upstream="shared", set={"stages.student.train.steps": 40,
                                                          "stages.student.train.checkpoint_every": 5,
                                                          "stages.student.train.eval_every": 40})
    done = distilkit("sweep", str(path), "-o", "slurm", "--launcher", "slurm", "--cpus-per-run", "1", "--mem", "2G",
                     "--time", "20", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    record = json.loads((tmp_path / "slurm" / "sw" / "slurm" / "jobs.json").read_text())
    assert len(record) == 5  # one teacher, two runs of each variant
    student = next(r for r in record if r["title"] == "dskd, seed 0")
    assert student["after"] == [next(r for r in record if r["title"].startswith("teacher"))["job_id"]]
    # preempt the distilled student once it has a checkpoint
    from distilkit.sweep.runner import SweepRun

    run_dir = SweepRun(path, tmp_path / "slurm", quiet=True).pipes["dskd", 0].run_dir("dskd")
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline and not (run_dir / "checkpoints" / "last.pt").is_file():
        time.sleep(0.2)
    assert job_state(student["job_id"])[0] == "RUNNING", "the student never started"
    assert not (run_dir / "summary.json").is_file(), "the student finished before it could be preempted"
    subprocess.run(["scancel", "--signal=TERM", "--full", student["job_id"]], check=True)
    while time.monotonic() < deadline and job_state(student["job_id"])[1] == 0:
        time.sleep(0.5)
    assert job_state(student["job_id"])[1] == 1, "the job did not requeue itself"
    # Slurm holds a requeued job back for two minutes; the test need not wait for that
    subprocess.run(["scontrol", "update", f"JobId={student['job_id']}", "StartTime=now"], check=False)
    done = distilkit("sweep", str(path), "-o", "slurm", "--wait", "-q", cwd=tmp_path)
    assert done.returncode == 0, done.stderr + done.stdout
    log = Path(student["log"]).read_text()
    assert "Requeued job" in log and "restart 1" in log, log
    status = distilkit("sweep", str(path), "-o", "slurm", "--status", cwd=tmp_path).stdout.strip().splitlines()
    assert len(status) == 5 and all(line.startswith("done") for line in status), status
    done = distilkit("sweep", str(path), "-o", "local", "--jobs", "2", "-q", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    a, b = tmp_path / "slurm" / "sw", tmp_path / "local" / "sw"
    assert table(a / "results.csv") == table(b / "results.csv")
    runs = sorted(p.parent.parent.name for p in a.glob("*/checkpoints/last.pt"))
    assert len(runs) == 5 and runs == sorted(p.parent.parent.name for p in b.glob("*/checkpoints/last.pt"))
    for name in runs:
        x = torch.load(a / name / "checkpoints" / "last.pt", weights_only=True)["student"]
        y = torch.load(b / name / "checkpoints" / "last.pt", weights_only=True)["student"]
        assert all(torch.equal(x[k], y[k]) for k in y), name
