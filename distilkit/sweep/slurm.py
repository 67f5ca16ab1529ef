"""``distilkit sweep FILE --launcher slurm``: every run of a sweep queued on a Slurm cluster at once, through submitit
(``pip install 'distilkit[slurm]'``).

What is submitted: one job per upstream task (the teachers: shared, or one per seed) and, for each set of variant
runs that need the same upstream jobs, one job array whose tasks wait on those jobs (``--dependency=afterok:...``,
``--kill-on-invalid-dep=yes``: a failed upstream job cancels its dependents instead of leaving them pending). A task
that is finished already is not submitted (:func:`schedule`; ``--plan`` prints these jobs and their sbatch scripts
without submitting: :mod:`distilkit.sweep.slurm_plan`). Each job runs the same ``distilkit run`` of the same recipe
on the same output folder as the local launcher, in a child process with as many threads as the CPUs Slurm gave the
job (``SLURM_CPUS_PER_TASK``), so the stage cache, the locks, resume and bitwise repeatability hold unchanged; with
``--gpus-per-run N`` > 1 the run is ``distilkit run --nproc-per-node N`` (torchrun inside the job: ranks, world size
and the master address are those of the job's node, the existing DDP path).

Preemption and time limits: the jobs are submitted with ``--signal=TERM@90`` and submitit's preemption signal set
to SIGTERM (``SUBMITIT_PREEMPT_SIGNAL``), so both a time limit's warning and a preemption (or ``scancel
--signal=TERM``) reach :meth:`RunJob.checkpoint`: the run finishes its step and writes ``last.pt``, and the job
requeues itself (``scontrol requeue``: same job id, so dependencies hold); the requeued job resumes from that
checkpoint and ends with the bits of an uninterrupted run. The job's Python replaces the batch shell (``exec``, no
``srun``): ``srun`` ends its step on SIGTERM and a shell dies of it, either of which would end the job before the
requeue; so the signal is sent to the batch shell (``--signal=B:TERM@90``), which is that Python.

What ran where is kept in ``<output>/<sweep>/slurm/jobs.json``; :mod:`distilkit.sweep.slurm_status` reads
the jobs' states from it.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError
from distilkit.sweep.slurm_status import status

EXTRA = "pip install 'distilkit[slurm]'"
PREEMPT_ENV = "SUBMITIT_PREEMPT_SIGNAL"
TIME_RE = re.compile(r"(?:(\d+)-)?(\d+(?::\d+){0,2})")


def submitit_module() -> Any:
    """submitit, or one line naming the extra that installs it."""
    try:
        import submitit
    except ImportError:
        raise DistilkitError(f"--launcher slurm needs submitit: {EXTRA}") from None
    return submitit


def minutes(value: str | int) -> int:
    """A Slurm time in whole minutes (seconds round up): ``MINUTES``, ``MINUTES:SECONDS``, ``HOURS:MINUTES:SECONDS``,
    ``DAYS-HOURS``, ``DAYS-HOURS:MINUTES``, ``DAYS-HOURS:MINUTES:SECONDS``."""
    text = str(value).strip()
    match = TIME_RE.fullmatch(text)
    if not match:
        raise DistilkitError(f"--time {text!r}: give minutes, H:MM:SS or D-HH:MM:SS (Slurm's forms)")
    parts = [int(p) for p in match.group(2).split(":")]
    if match.group(1) is None:
        if len(parts) == 1:
            total, secs = parts[0], 0
        elif len(parts) == 2:
            total, secs = parts
        else:
            total, secs = parts[0] * 60 + parts[1], parts[2]
    else:
        hours, mins, secs = parts + [0] * (3 - len(parts))
        total = int(match.group(1)) * 1440 + hours * 60 + mins
    return total + (1 if secs else 0)


@dataclass
class Resources:
    """One run's allocation: the command line's values over the sweep file's ``launcher:`` block."""

    gpus: int = 0
    cpus: int = 1
    mem: str | None = None
    time: int = 240  # minutes; a run longer than this is requeued from its checkpoint
    partition: str | None = None
    extra: dict[str, str] = field(default_factory=dict)  # any other sbatch option: account, qos, constraint, ...
    array_parallelism: int = 64

    @staticmethod
    def merge(block: Any, cli: dict[str, Any]) -> "Resources":
        """``block`` (the sweep file's ``launcher:``, or None) with the command line's values (None: not given)."""
        base = block.model_dump() if block is not None else {}
        want = {"gpus": base.get("gpus_per_run"), "cpus": base.get("cpus_per_run"), "mem": base.get("mem"),
                "time": base.get("time"), "partition": base.get("partition"),
                "array_parallelism": base.get("array_parallelism")}
        for key, value in cli.items():
            if value is not None and key != "extra":
                want[key] = value
        extra = {str(k): str(v) for k, v in (base.get("slurm") or {}).items()}
        extra.update(cli.get("extra") or {})
        out = Resources(**{k: v for k, v in want.items() if v is not None}, extra=extra)
        out.time = minutes(out.time)
        if out.gpus < 0 or out.cpus < 1 or out.array_parallelism < 1:
            raise DistilkitError(f"launcher: gpus per run {out.gpus}, cpus per run {out.cpus}, array parallelism "
                                 f"{out.array_parallelism}: give gpus >= 0, cpus >= 1, parallelism >= 1")
        return out


def parse_slurm_options(values: list[str] | None) -> dict[str, str]:
    """``--slurm KEY=VALUE`` (repeated) as sbatch options (``account=lab``, ``qos=high``)."""
    out: dict[str, str] = {}
    for item in values or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise DistilkitError(f"--slurm {item!r}: give KEY=VALUE (an sbatch option, e.g. account=mylab)")
        out[key.strip().lstrip("-")] = value.strip()
    return out


class RunJob:
    """The body of one Slurm job (pickled by submitit): ``distilkit ARGV`` in a child process with the job's CPUs as
    its threads; :meth:`checkpoint` (on SIGTERM) lets the run finish its step and write ``last.pt``, then submitit
    requeues the job with this same body, which resumes."""

    def __init__(self, argv: list[str], grace: float = 10.0) -> None:
        self.argv = list(argv)
        self.grace = grace  # seconds the run has to stop on the signal it got before it is sent one
        self._child: subprocess.Popen | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {"argv": self.argv, "grace": self.grace}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.argv, self.grace, self._child = state["argv"], state.get("grace", 10.0), None

    def __call__(self) -> int:
        from distilkit.engine.train.stop import PARENT_ENV

        threads = os.environ.get("SLURM_CPUS_PER_TASK") or "1"
        env = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, PARENT_ENV: str(os.getpid())}
        print(f"distilkit {' '.join(self.argv)} (threads {threads}, job {os.environ.get('SLURM_JOB_ID', '?')}, "
              f"restart {os.environ.get('SLURM_RESTART_COUNT', '0')})", flush=True)
        self._child = subprocess.Popen([sys.executable, "-m", "distilkit", *self.argv], env=env)
        code = self._child.wait()
        if code != 0:
            raise RuntimeError(f"distilkit {' '.join(self.argv)}: exit status {code}")
        return code

    def checkpoint(self) -> Any:
        """Called by submitit on the preemption signal: the run stops after its step with ``last.pt`` written (it
        got the signal too; if not, it is sent one), then the job is requeued with a fresh body."""
        from submitit.helpers import DelayedSubmission

        child = self._child
        if child is not None and not _reaped(child, self.grace):  # the signal reached only this process: pass it on
            child.send_signal(signal.SIGTERM)
            _reaped(child, None)
        print(f"checkpointed (run exit status {child.returncode if child else None}); requeueing", flush=True)
        # Slurm's requeue signals the job again while `scontrol requeue` waits: ignored (handled: "pending execution")
        for name in {"SIGTERM", f"SIG{os.environ.get(PREEMPT_ENV, 'TERM')}"} & set(dir(signal)):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
        return DelayedSubmission(RunJob(self.argv, self.grace))


def _reaped(child: subprocess.Popen, timeout: float | None) -> bool:
    """Whether ``child`` has exited within ``timeout`` seconds (None: wait for it), by ``os.waitpid`` polling rather
    than ``Popen.wait``: a scheduler may deliver one signal twice, and a handler that interrupts another's
    ``Popen.wait`` would block on its lock for good."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while child.returncode is None:
        try:
            pid, code = os.waitpid(child.pid, os.WNOHANG)
        except ChildProcessError:  # reaped already (by the interrupted wait)
            return True
        if pid:
            child.returncode = os.waitstatus_to_exitcode(code)
            return True
        if deadline is not None and time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


@dataclass
class Submitted:
    """One submitted task: what it runs and where its job writes."""

    title: str
    variant: str
    seed: int
    stages: list[str]
    job_id: str
    log: str
    after: list[str]


def _setup_signal() -> None:
    """SIGTERM as submitit's preemption signal, in this process (the ``--signal`` line) and in the jobs (the
    environment sbatch exports)."""
    os.environ.setdefault(PREEMPT_ENV, "TERM")
    from submitit.core.job_environment import JobEnvironment

    JobEnvironment.USR_SIG = os.environ[PREEMPT_ENV]


def job_python() -> str:
    """The job's Python, which replaces the batch shell (``exec``, no srun): a signal to the job or to the batch
    shell (B:TERM@90 before the time limit) reaches it, and no shell or srun ends the job before it has requeued."""
    return f"exec {shlex.quote(sys.executable)}"


def sbatch_parameters(res: Resources, name: str, after: list[str], signal_name: str) -> dict[str, Any]:
    """The parameters of one job (submitit's ``SlurmExecutor.update_parameters``), waiting on the jobs ``after``."""
    extra: dict[str, Any] = {"kill-on-invalid-dep": "yes", "requeue": True, "signal": f"B:{signal_name}@90",
                             **res.extra}
    params: dict[str, Any] = {"job_name": f"distilkit-{name}", "cpus_per_task": res.cpus, "ntasks_per_node": 1,
                              "nodes": 1, "time": res.time, "array_parallelism": res.array_parallelism,
                              "stderr_to_stdout": True, "use_srun": False, "additional_parameters": extra}
    optional = {"gpus_per_node": res.gpus, "mem": res.mem, "partition": res.partition,
                "dependency": "afterok:" + ":".join(after) if after else None}
    return {**params, **{k: v for k, v in optional.items() if v}}


def _executor(submitit: Any, folder: Path, res: Resources, name: str, after: list[str]) -> Any:
    ex = submitit.SlurmExecutor(folder=str(folder / "%j"), max_num_timeout=100, python=job_python())
    ex.update_parameters(**sbatch_parameters(res, name, after, os.environ[PREEMPT_ENV]))
    return ex


@dataclass
class PlannedJob:
    """One job a submission queues: a single task, or an array of tasks (more than one) that wait on the same
    upstream jobs (``after``: keys of earlier planned jobs, or ids of jobs queued before)."""

    key: str  # job-1, job-2, ...: the plan's name for the id Slurm gives it
    tasks: list[Any]
    after: list[str]


def schedule(run: Any, queued: dict[tuple[str, int, tuple[str, ...]], str] | None = None) -> list[PlannedJob]:
    """The jobs :func:`submit` queues for ``run``: one per unfinished upstream task, then one per set of unfinished
    variant tasks needing the same upstream jobs; ``queued`` (a task's key -> job id) are not queued again. Runs
    nothing."""
    queued = queued or {}
    jobs: list[PlannedJob] = []
    upstream_job: dict[tuple[str, ...], str] = {}  # the upstream runs' folders -> the job that trains them
    for task in run.upstream_tasks():
        if run.finished(task):
            continue
        key = run.upstream_key(task)
        if task.key in queued:
            upstream_job[key] = queued[task.key]
            continue
        upstream_job[key] = f"job-{len(jobs) + 1}"
        jobs.append(PlannedJob(upstream_job[key], [task], []))
    groups: dict[tuple[str, ...], list[Any]] = {}
    for task in run.variant_tasks():
        if run.finished(task) or task.key in queued:
            continue
        key = run.upstream_key(task)
        groups.setdefault((upstream_job[key],) if key in upstream_job else (), []).append(task)
    for after, tasks in groups.items():
        jobs.append(PlannedJob(f"job-{len(jobs) + 1}", tasks, list(after)))
    return jobs


def job_argv(run: Any, task: Any, res: Resources) -> list[str]:
    """What a job's body runs (``distilkit ARGV``), with absolute paths: the job may start elsewhere on the shared
    file system; with several GPUs, ``--nproc-per-node`` (torchrun inside the job)."""
    extra = ["--nproc-per-node", str(res.gpus)] if res.gpus > 1 else []
    return [*replace(task, recipe_file=task.recipe_file.resolve()).argv(run.output.resolve()), "--quiet", *extra]


def submit(run: Any, res: Resources) -> list[Submitted]:
    """Queue the unfinished tasks of ``run`` (a :class:`~distilkit.sweep.runner.SweepRun`) as :func:`schedule` plans
    them (upstream jobs, then the variants' arrays that wait on them); written to ``slurm/jobs.json``, returned."""
    submitit = submitit_module()
    _setup_signal()
    run.write_recipes()
    folder = run.root / "slurm"
    folder.mkdir(parents=True, exist_ok=True)
    queued = {s.key: s.job_id for s in (status(run) if (folder / "jobs.json").is_file() else [])
              if s.state in ("pending", "running")}  # submitted before and still queued: not again
    ids: dict[str, str] = {}  # planned job key -> Slurm's job id
    submitted: list[Submitted] = []
    for planned in schedule(run, queued):
        after = [ids.get(a, a) for a in planned.after]
        ex = _executor(submitit, folder, res, run.sweep.name, after)
        with ex.batch():  # one task: a plain job; several: an array
            jobs = [ex.submit(RunJob(job_argv(run, t, res))) for t in planned.tasks]
        ids[planned.key] = jobs[0].job_id
        submitted += [Submitted(t.title, t.variant, t.seed, list(t.stages), job.job_id, str(job.paths.stdout), after)
                      for t, job in zip(planned.tasks, jobs)]
    record = folder / "jobs.json"
    previous = json.loads(record.read_text(encoding="utf-8")) if record.is_file() else []
    from distilkit.files import atomic_write_text

    atomic_write_text(record, json.dumps(previous + [asdict(s) for s in submitted], indent=1))
    return submitted


__all__ = ["EXTRA", "PlannedJob", "Resources", "RunJob", "Submitted", "job_argv", "minutes", "parse_slurm_options",
           "sbatch_parameters", "schedule", "submit"]
