"""``distilkit sweep FILE --launcher slurm --plan``: the jobs a submission would queue (:func:`~distilkit.sweep.slurm.
schedule`), their ``afterok`` dependencies and the sbatch scripts submitit would write for them, built without an
executor (submitit's ``SlurmExecutor`` needs ``srun`` on PATH), without running any Slurm command and without
writing anything. A job is named ``job-N`` until Slurm gives it an id.
"""

from __future__ import annotations

import os
import shlex
from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError
from distilkit.sweep.slurm import (EXTRA, PREEMPT_ENV, PlannedJob, Resources, job_argv, job_python, sbatch_parameters,
                                   schedule, submitit_module)


def sbatch_script(folder: Path, params: dict[str, Any], tasks: int) -> str:
    """The sbatch script submitit writes for a job of ``tasks`` tasks (an array when more than one) with ``params``,
    built as its executor builds it but without one (an executor needs ``srun`` on PATH) and without writing."""
    try:
        from submitit.slurm.slurm import _make_sbatch_string
    except ImportError as exc:
        raise DistilkitError(f"--plan --launcher slurm: this submitit cannot build sbatch scripts ({exc}); "
                             f"{EXTRA}") from None
    job_folder = (folder / "%j").expanduser().absolute()
    command = " ".join([job_python(), "-u -m submitit.core._submit", shlex.quote(str(job_folder))])
    return _make_sbatch_string(command=command, folder=job_folder, map_count=tasks if tasks > 1 else None, **params)


def plan(run: Any, res: Resources) -> list[tuple[PlannedJob, str]]:
    """Each job :func:`submit` would queue now with its sbatch script (dependencies on the plan's job keys): no
    executor, no Slurm command, nothing written. Tasks queued before are listed too (only ``squeue`` could say)."""
    submitit_module()
    folder = (run.root / "slurm").resolve()
    signal_name = os.environ.get(PREEMPT_ENV, "TERM")
    return [(job, sbatch_script(folder, sbatch_parameters(res, run.sweep.name, job.after, signal_name),
                                len(job.tasks))) for job in schedule(run)]


def _named_tasks(job: PlannedJob) -> list[tuple[str, Any]]:
    """(name, task) of a planned job's tasks: ``job-2_0``, ``job-2_1``, ... in an array, else the job's key."""
    return [(f"{job.key}_{i}" if len(job.tasks) > 1 else job.key, task) for i, task in enumerate(job.tasks)]


def describe_plan(run: Any, res: Resources, jobs: list[tuple[PlannedJob, str]]) -> str:
    """The plan as text: what would be queued, the dependency graph, each task's command and each sbatch script."""
    runs = len(run.variant_tasks())
    todo = sum(len(j.tasks) for j, _ in jobs if j.tasks[0].stages == (j.tasks[0].variant,))
    lines = [f"Slurm plan for sweep {run.sweep.name}: nothing submitted, nothing written, no Slurm command run.",
             f"Without --plan, this command queues {len(jobs)} job(s) for {todo} of the sweep's {runs} runs "
             f"({runs - todo} finished; each {res.cpus} CPU(s), {res.gpus} GPU(s), {res.time} min),",
             f"after writing the variants' recipes to {(run.root / 'recipes').resolve()};",
             f"the jobs write under {(run.root / 'slurm').resolve()}."]
    if (run.root / "slurm" / "jobs.json").is_file():
        lines += [f"Jobs were submitted before ({run.root / 'slurm' / 'jobs.json'}): the submission asks squeue which "
                  "are still queued", "and does not queue those again; this plan asks nothing, so it lists them."]
    if not jobs:
        return "\n".join([*lines, "", "Every run is finished: nothing to submit."])
    width = max(len(name) for job, _ in jobs for name, _ in _named_tasks(job))
    lines += ["", "Dependency graph (job-N: the id Slurm gives the N-th job when it is submitted):"]
    for job, _ in jobs:
        size = (f"array of {len(job.tasks)} tasks (0-{len(job.tasks) - 1}, "
                f"{min(len(job.tasks), res.array_parallelism)} at a time)" if len(job.tasks) > 1 else "1 task")
        lines.append(f"  {job.key}  distilkit-{run.sweep.name}  {size}  "
                     + (f"afterok:{':'.join(job.after)}" if job.after else "waits on nothing"))
        lines += [f"    {name:<{width}}  {task.title}" for name, task in _named_tasks(job)]
    lines += ["", "Commands (what each task runs, in its job's Python):"]
    lines += [f"  {name:<{width}}  distilkit {shlex.join(job_argv(run, task, res))}" for job, _ in jobs
              for name, task in _named_tasks(job)]
    for job, script in jobs:
        lines += ["", f"sbatch script of {job.key}:", *(f"  {ln}" if ln else "" for ln in script.rstrip().splitlines())]
    return "\n".join(lines)


__all__ = ["describe_plan", "plan", "sbatch_script"]
