"""``distilkit sweep --launcher slurm`` without a cluster: what it submits, read from recording ``sbatch``,
``squeue`` and ``scontrol`` programs put first on PATH (each writes what it was given and answers as Slurm does);
the requeue handler against a real ``distilkit run``; the extra named when submitit is missing. The same on a real
Slurm: tests/test_slurm_real.py (slow)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from test_sweep import write_sweep
from distilkit.cli import main

SBATCH = r"""#!/usr/bin/env bash
# records the submission script it is given and answers as sbatch does
dir="$(dirname "$0")"
n=$(( $(cat "$dir/count" 2>/dev/null || echo 100) + 1 ))
echo "$n" > "$dir/count"
cp "$1" "$dir/sbatch-$n.sh"
echo "Submitted batch job $n"
"""
SQUEUE = r"""#!/usr/bin/env bash
# lists every recorded job as pending (array tasks too), in the format asked for (%i|%T|%r)
dir="$(dirname "$0")"
for f in "$dir"/sbatch-*.sh; do
  n=${f##*/sbatch-}; n=${n%.sh}
  if grep -q -- "--array=0-1" "$f"; then echo "${n}_0|PENDING|Dependency"; echo "${n}_1|PENDING|Dependency";
  else echo "$n|PENDING|Priority"; fi
done
"""
SCONTROL = r"""#!/usr/bin/env bash
echo "JobId=$3 JobState=FAILED Reason=NonZeroExitCode"
"""
NEVER = r"""#!/bin/sh
# a Slurm command a plan must not call: leaves a mark (shell builtins only: PATH may hold nothing else) and fails
: > "${0%/*}/called-${0##*/}"
exit 1
"""
SLURM_COMMANDS = ("sbatch", "srun", "squeue", "scontrol", "scancel")


@pytest.fixture
def slurm_bin(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder first on PATH with the recording sbatch (and squeue / scontrol answering from its records), and an
    ``srun`` that fails if run: submitit's executor looks for it on PATH before it submits anything (a machine
    without Slurm has none; one where .ci/slurm-up ran earlier has the real one), and a submission never runs it."""
    folder = tmp_path / "bin"
    folder.mkdir()
    srun = "#!/bin/sh\necho 'srun: not expected at submission' >&2\nexit 1\n"
    for name, text in (("sbatch", SBATCH), ("squeue", SQUEUE), ("scontrol", SCONTROL), ("srun", srun)):
        (folder / name).write_text(text)
        (folder / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")
    return folder


def options(script: str) -> dict[str, str]:
    return dict(re.findall(r"^#SBATCH --([a-z-]+)(?:=(.*))?$", script, flags=re.M))


def test_the_plan_queues_upstream_first_then_arrays_that_wait_on_it(tmp_path, slurm_bin, capsys) -> None:
    path = write_sweep(tmp_path, upstream="shared", launcher={"cpus_per_run": 3, "mem": "3G", "partition": "cpu",
                                                              "slurm": {"account": "lab", "qos": "low"}})
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "--launcher", "slurm", "--cpus-per-run", "2", "--time",
                 "1-02:00:00", "--slurm", "qos=high", "constraint=avx2"]) == 0
    printed = capsys.readouterr().out
    scripts = {int(p.stem.split("-")[1]): p.read_text() for p in slurm_bin.glob("sbatch-*.sh")}
    assert sorted(scripts) == [101, 102, 103]  # the teacher, then one array per set of upstream jobs
    teacher, plain, distilled = (options(scripts[n]) for n in (101, 102, 103))
    assert "dependency" not in teacher and "array" not in teacher
    assert "dependency" not in plain and plain["array"] == "0-1%2"  # `none` distils from nothing: it waits for none
    assert distilled["dependency"] == "afterok:101" and distilled["array"] == "0-1%2"
    for opts in (teacher, plain, distilled):
        # the command line wins over the sweep file's launcher block, which gives the rest
        assert opts["cpus-per-task"] == "2" and opts["mem"] == "3G" and opts["partition"] == "cpu"
        assert opts["account"] == "lab" and opts["qos"] == "high" and opts["constraint"] == "avx2"
        assert opts["time"] == str(26 * 60) and opts["signal"] == "B:TERM@90" and "requeue" in opts
        assert opts["kill-on-invalid-dep"] == "yes" and opts["ntasks-per-node"] == "1"
    assert f"exec {sys.executable}" in scripts[101]  # the job's Python replaces the batch shell, no srun
    assert "srun" not in scripts[101]
    record = json.loads((out / "sw" / "slurm" / "jobs.json").read_text())
    assert [(r["title"], r["job_id"], r["after"]) for r in record] == [
        ("teacher (upstream of variant dskd), seed 0", "101", []), ("none, seed 0", "102_0", []),
        ("none, seed 1", "102_1", []),
        ("dskd, seed 0", "103_0", ["101"]), ("dskd, seed 1", "103_1", ["101"])]
    assert "103_1  dskd, seed 1 after 101" in printed
    # each job runs the same `distilkit run` as the local launcher, with absolute paths
    from submitit.core.utils import DelayedSubmission

    body = DelayedSubmission.load(out / "sw" / "slurm" / "103_1" / "103_1_submitted.pkl").function
    assert body.argv == ["run", str((out / "sw" / "recipes" / "dskd.yaml").resolve()), "--seed", "1", "--output",
                         str(out.resolve()), "--stage", "dskd", "--quiet"]
    # --status: squeue's states; a second submission queues nothing that is queued already
    assert main(["sweep", str(path), "-o", str(out), "--status"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 5 and all(line.startswith("pending") for line in lines), lines
    assert main(["sweep", str(path), "-o", str(out), "--launcher", "slurm"]) == 0
    assert len(list(slurm_bin.glob("sbatch-*.sh"))) == 3
    # a queued task is known by its variant, seed and stages, not by its title (a title may be worded otherwise)
    jobs = out / "sw" / "slurm" / "jobs.json"
    jobs.write_text(json.dumps([{**r, "title": f"old words {i}"} for i, r in enumerate(json.loads(jobs.read_text()))]))
    assert main(["sweep", str(path), "-o", str(out), "--launcher", "slurm"]) == 0
    assert len(list(slurm_bin.glob("sbatch-*.sh"))) == 3


def never_called_bin(folder: Path, names: tuple[str, ...] = SLURM_COMMANDS) -> Path:
    """``folder`` with a stand-in for each Slurm command in ``names`` that leaves ``called-NAME`` beside it if run."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        (folder / name).write_text(NEVER)
        (folder / name).chmod(0o755)
    return folder


def called(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.glob("called-*"))


def files_under(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


class NoProcess:
    """subprocess.Popen for a test in which nothing may start a process: records the attempt and refuses."""

    attempts: list[Any] = []

    def __init__(self, args: Any, *rest: Any, **kwargs: Any) -> None:
        NoProcess.attempts.append(args)
        raise AssertionError(f"a process was started: {args}")


@pytest.fixture
def no_slurm(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Stand-ins for sbatch/srun/squeue/scontrol/scancel first on PATH that mark themselves if called, no process
    may start (subprocess.Popen refuses), and the working folder is an empty one (to see that nothing is written)."""
    folder = never_called_bin(tmp_path / "bin")
    monkeypatch.setenv("PATH", f"{folder}{os.pathsep}{os.environ['PATH']}")
    NoProcess.attempts = []
    monkeypatch.setattr(subprocess, "Popen", NoProcess)
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return folder


def test_the_slurm_plan_prints_jobs_arrays_afterok_and_scripts_and_calls_and_writes_nothing(
        tmp_path, no_slurm, capsys) -> None:
    path = write_sweep(tmp_path, upstream="shared", launcher={"mem": "3G", "slurm": {"account": "lab"}})
    before = files_under(tmp_path)
    out = tmp_path / "runs"
    for extra in ([], ["--wait"]):  # --wait with --plan: nothing submitted, nothing waited for
        assert main(["sweep", str(path), "-o", str(out), "--launcher", "slurm", "--plan", "--cpus-per-run", "2",
                     *extra]) == 0
        captured = capsys.readouterr()
        assert "Traceback" not in captured.err
        text = captured.out
        assert called(no_slurm) == [] and NoProcess.attempts == []
        assert files_under(tmp_path) == before and not out.exists()  # nothing written, anywhere
        assert "Slurm plan for sweep sw: nothing submitted, nothing written, no Slurm command run." in text
        assert "queues 3 job(s) for 4 of the sweep's 4 runs (0 finished; each 2 CPU(s), 0 GPU(s), 240 min)" in text
        graph = text.split("Dependency graph")[1].split("Commands")[0]
        assert re.search(r"job-1  distilkit-sw  1 task  waits on nothing\n"
                         r" +job-1 +teacher \(upstream of variant dskd\), seed 0\n", graph), graph
        assert re.search(r"job-2  distilkit-sw  array of 2 tasks \(0-1, 2 at a time\)  waits on nothing\n"
                         r" +job-2_0 +none, seed 0\n +job-2_1 +none, seed 1\n", graph), graph
        assert re.search(r"job-3  distilkit-sw  array of 2 tasks \(0-1, 2 at a time\)  afterok:job-1\n"
                         r" +job-3_0 +dskd, seed 0\n +job-3_1 +dskd, seed 1\n", graph), graph
        recipe = (out / "sw" / "recipes" / "dskd.yaml").resolve()
        assert f"  job-3_1  distilkit run {recipe} --seed 1 --output {out.resolve()} --stage dskd --quiet\n" in text
        scripts = {m.group(1): options(textwrap.dedent(m.group(2))) for m in
                   re.finditer(r"sbatch script of (job-\d):\n(.*?)(?=\n\nsbatch script|\Z)", text, flags=re.S)}
        assert sorted(scripts) == ["job-1", "job-2", "job-3"]
        assert "dependency" not in scripts["job-1"] and "array" not in scripts["job-1"]
        assert "dependency" not in scripts["job-2"] and scripts["job-2"]["array"] == "0-1%2"
        assert scripts["job-3"]["dependency"] == "afterok:job-1" and scripts["job-3"]["array"] == "0-1%2"
        assert all(o["cpus-per-task"] == "2" and o["mem"] == "3G" and o["account"] == "lab" for o in scripts.values())
    assert main(["sweep", str(path), "-o", str(out), "--plan", "--status"]) == 2  # --status would ask squeue
    err = capsys.readouterr().err
    assert "--plan and --status: give one" in err and len(err.strip().splitlines()) == 1
    assert called(no_slurm) == [] and files_under(tmp_path) == before


def test_a_shared_upstream_job_is_named_by_the_variants_it_is_upstream_of(tmp_path, no_slurm, capsys) -> None:
    """Not "teacher (for none)" — the first variant's name read as if the job were for nobody — but the variants
    whose runs wait on it: one, several, or every variant of the sweep."""
    from distilkit.sweep.runner import SweepRun

    kd = {"distill": [{"name": "kd", "weight": 1}]}
    several = write_sweep(tmp_path, upstream="shared", seeds=[0], variants={
        "none": {"distill": []}, "dskd": {"distill": [{"name": "dskd", "weight": 10}]}, "kd": kd})
    assert [t.title for t in SweepRun(several, tmp_path / "runs", quiet=True).upstream_tasks()] == [
        "teacher (upstream of variants dskd, kd), seed 0"]
    every = write_sweep(tmp_path, upstream="shared", seeds=[0], variants={"kd": kd, "kd2": {**kd, "label": "2"}})
    assert main(["sweep", str(every), "-o", str(tmp_path / "runs"), "--launcher", "slurm", "--plan"]) == 0
    assert re.search(r"job-1 +teacher \(upstream of every variant\), seed 0\n", capsys.readouterr().out)


def test_the_local_plan_starts_nothing_and_writes_only_the_recipes_it_names(tmp_path, no_slurm, capsys) -> None:
    path = write_sweep(tmp_path, seeds=[0])
    out = tmp_path / "runs"
    for extra in (["--jobs", "2"], ["--wait"]):
        assert main(["sweep", str(path), "-o", str(out), "--plan", *extra]) == 0
        captured = capsys.readouterr()
        assert len(captured.out.strip().splitlines()) == 3 and "Traceback" not in captured.err
        assert f"recipes they run were written to {out / 'sw' / 'recipes'}" in captured.err
        assert called(no_slurm) == [] and NoProcess.attempts == []
        assert files_under(out) == {"sw", "sw/recipes", "sw/recipes/none.yaml", "sw/recipes/dskd.yaml"}
        assert not list((tmp_path / "cwd").iterdir())


def test_the_slurm_plan_runs_without_srun_on_path(tmp_path, monkeypatch, capsys) -> None:
    """A machine with submitit and no Slurm: PATH holds only stand-ins of the other Slurm commands (no srun; submitit
    looks for it on PATH when its executor is built, in this process); nothing is called or written."""
    folder = never_called_bin(tmp_path / "bin", ("sbatch", "squeue", "scontrol", "scancel"))
    path = write_sweep(tmp_path)
    before = files_under(tmp_path)
    out = tmp_path / "runs"
    monkeypatch.setenv("PATH", str(folder))
    monkeypatch.chdir(tmp_path)
    code = main(["sweep", str(path), "-o", str(out), "--launcher", "slurm", "--plan"])
    done = capsys.readouterr()
    assert code == 0, done.err
    assert "Traceback" not in done.err and "srun" not in done.err
    assert "Slurm plan for sweep sw" in done.out and "#SBATCH --dependency=afterok:job-1" in done.out
    assert called(folder) == [] and files_under(tmp_path) == before


def test_the_plan_shows_the_scripts_a_submission_then_queues(tmp_path, slurm_bin, capsys, monkeypatch) -> None:
    """The plan's sbatch scripts are those sbatch gets at the submission, once job-N is read as Slurm's id; a plan
    after a submission asks squeue nothing and says that queued jobs are not queued again."""
    path = write_sweep(tmp_path, upstream="per_seed", launcher={"gpus_per_run": 2, "partition": "gpu"})
    out = tmp_path / "runs"
    argv = ["sweep", str(path), "-o", str(out), "--launcher", "slurm", "--time", "90"]
    assert main([*argv, "--plan"]) == 0
    text = capsys.readouterr().out
    assert not list(slurm_bin.glob("sbatch-*.sh"))
    planned = {int(m.group(1)) + 100: textwrap.dedent(m.group(2)).strip() for m in
               re.finditer(r"sbatch script of job-(\d+):\n(.*?)(?=\n\nsbatch script|\Z)", text, flags=re.S)}
    assert main(argv) == 0
    capsys.readouterr()
    sent = {int(p.stem.split("-")[1]): p.read_text().strip() for p in slurm_bin.glob("sbatch-*.sh")}
    # a teacher per seed, the array of `none` (waits on nothing), a `dskd` job per seed after its seed's teacher
    assert sorted(planned) == sorted(sent) == [101, 102, 103, 104, 105]
    assert "job-4  distilkit-sw  1 task  afterok:job-1" in text and "job-5  distilkit-sw  1 task  afterok:job-2" in text
    for n, script in planned.items():
        assert re.sub(r"afterok:job-(\d+)", lambda m: f"afterok:{int(m.group(1)) + 100}", script) == sent[n]
    assert "--nproc-per-node 2" in text
    never_called_bin(slurm_bin, ("squeue", "scontrol"))  # from now on, asking Slurm leaves a mark
    assert main([*argv, "--plan"]) == 0
    assert "Jobs were submitted before" in capsys.readouterr().out and called(slurm_bin) == []


def test_a_job_that_left_the_queue_without_its_run_is_failed_with_its_logs_last_line(tmp_path, slurm_bin,
                                                                                      capsys) -> None:
    path = write_sweep(tmp_path, seeds=[0])
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "--launcher", "slurm", "--gpus-per-run", "2"]) == 0
    capsys.readouterr()
    scripts = {int(p.stem.split("-")[1]): p.read_text() for p in slurm_bin.glob("sbatch-*.sh")}
    assert all(options(s)["gpus-per-node"] == "2" for s in scripts.values())
    record = json.loads((out / "sw" / "slurm" / "jobs.json").read_text())
    assert all(r["job_id"] for r in record)
    (slurm_bin / "squeue").write_text("#!/usr/bin/env bash\n")  # nothing queued any more
    teacher = next(r for r in record if r["title"].startswith("teacher"))
    Path(teacher["log"]).parent.mkdir(parents=True, exist_ok=True)
    Path(teacher["log"]).write_text("starting\nRuntimeError: distilkit run ...: exit status 2\n")
    assert main(["sweep", str(path), "-o", str(out), "--status"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    by_title = {re.split(r"\s+", line, maxsplit=2)[2].split("  log")[0]: line for line in lines}
    teacher_line = by_title["teacher (upstream of variant dskd), seed 0"]
    assert "FAILED: RuntimeError: distilkit run ...: exit status 2" in teacher_line
    assert "never ran: the upstream job" in by_title["dskd, seed 0"]
    from submitit.core.utils import DelayedSubmission

    body = DelayedSubmission.load(Path(teacher["log"]).parent / f"{teacher['job_id']}_submitted.pkl").function
    assert body.argv[-2:] == ["--nproc-per-node", "2"]  # several GPUs: the existing DDP path inside the job


def test_launcher_problems_are_one_line(tmp_path, slurm_bin, capsys) -> None:
    path = write_sweep(tmp_path)
    out = str(tmp_path / "r")
    for argv, why in ((["--launcher", "slurm", "--time", "2 hours"], "--time '2 hours': give minutes, H:MM:SS or "
                                                                       "D-HH:MM:SS"),
                      (["--launcher", "slurm", "--slurm", "account"], "--slurm 'account': give KEY=VALUE"),
                      (["--launcher", "slurm", "--status"], "no Slurm jobs recorded for sweep sw")):
        assert main(["sweep", str(path), "-o", out, *argv]) == 2
        err = capsys.readouterr().err
        assert why in err and len(err.strip().splitlines()) == 1, err
    bad = yaml.safe_load(path.read_text())
    bad["launcher"] = {"cpus": 2}
    path.write_text(yaml.safe_dump(bad))
    assert main(["sweep", str(path), "-o", out, "--launcher", "slurm"]) == 2
    assert "launcher.cpus" in capsys.readouterr().err
    assert not list(slurm_bin.glob("sbatch-*.sh"))  # nothing was submitted


def test_without_submitit_the_slurm_launcher_names_the_extra(tmp_path, monkeypatch, capsys) -> None:
    """submitit not importable (None in sys.modules: ``import submitit`` fails, as where it is not installed; the
    launcher imports it when it is asked for): one line naming the extra, exit status 2."""
    path = write_sweep(tmp_path)
    monkeypatch.setitem(sys.modules, "submitit", None)
    code = main(["sweep", str(path), "-o", str(tmp_path / "r"), "--launcher", "slurm"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "--launcher slurm needs submitit: pip install 'distilkit[slurm]'" in err
    assert len(err.strip().splitlines()) == 1, err


def _forked_run(argv: list[str]) -> Any:
    """``distilkit ARGV`` in a process forked from this one, with one thread (as RunJob gives its run, and as GNU
    OpenMP needs in a forked child); a handle with what RunJob reads of a ``subprocess.Popen``. On a machine with a
    GPU, where a forked child cannot train (conftest.can_fork), a ``distilkit`` process started as RunJob starts it."""
    from conftest import can_fork

    if not can_fork():
        return subprocess.Popen([sys.executable, "-m", "distilkit", *argv],
                                env={**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})
    pid = os.fork()
    if pid == 0:  # the child: the run, then out without this process's exit handlers
        code = 1
        try:
            import torch

            torch.set_num_threads(1)
            code = main(argv)
        except BaseException:  # noqa: BLE001  what a process would print
            import traceback

            traceback.print_exc()
        finally:
            os._exit(code)
    return SimpleNamespace(pid=pid, returncode=None, send_signal=lambda signum: os.kill(pid, signum))


def test_the_requeue_handler_stops_the_run_with_its_checkpoint_and_the_requeued_body_ends_with_the_same_bits(
        tmp_path) -> None:
    """RunJob.checkpoint as submitit calls it on SIGTERM, against a real `distilkit run`: the run that did not get the
    signal itself is sent one, stops after its step with last.pt, and the body handed back for the requeue resumes
    it to the bits of an uninterrupted run (made in this process: the bits do not depend on it). Over 3 s: two
    `distilkit run` processes are its point (the first forked from this one, the requeued one started by RunJob)."""
    import time

    import torch

    from conftest import tiny_recipe
    from distilkit.sweep.slurm import RunJob

    steps = 24  # the signal comes about 0.15 s after the first last.pt (step 4): 20 steps of margin, ~0.9 s of CPU
    recipe = tiny_recipe(steps=steps, distill=False)
    recipe["stages"]["teacher"]["train"].update({"checkpoint_every": 4, "eval_every": steps, "log_every": 8})
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    argv = ["run", str(tmp_path / "r.yaml"), "--output", str(tmp_path / "a"), "--quiet"]
    job = RunJob(argv, grace=0.1)  # the run did not get the signal itself: the grace is only waited out
    job._child = _forked_run(argv)
    deadline = time.monotonic() + 120
    while not list((tmp_path / "a").rglob("last.pt")) and time.monotonic() < deadline:
        time.sleep(0.02)
    handler = signal.getsignal(signal.SIGTERM)
    try:
        again = job.checkpoint().function
        # requeueing: a second SIGTERM (Slurm's requeue signals the job again) is ignored from here on
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, handler)  # this test process goes on
    assert job._child.returncode is not None  # it had stopped before the handler returned
    last = next((tmp_path / "a").rglob("last.pt"))
    stopped_at = torch.load(last, weights_only=True)["step"]
    assert 0 < stopped_at < steps and not list((tmp_path / "a").rglob("summary.json"))
    assert isinstance(again, RunJob) and again.argv == argv
    os.environ.update({"SLURM_CPUS_PER_TASK": "1"})
    try:
        assert again() == 0  # the requeued job: resumes
    finally:
        os.environ.pop("SLURM_CPUS_PER_TASK")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the uninterrupted run, in this process with one thread as the runs in theirs
    try:
        assert main(["run", str(tmp_path / "r.yaml"), "--output", str(tmp_path / "b"), "--quiet"]) == 0
    finally:
        torch.set_num_threads(threads)
    a = torch.load(next((tmp_path / "a").rglob("last.pt")), weights_only=True)
    b = torch.load(next((tmp_path / "b").rglob("last.pt")), weights_only=True)
    assert a["step"] == b["step"] == steps
    assert all(torch.equal(a["student"][k], b["student"][k]) for k in b["student"])
