"""The states of a sweep's Slurm jobs (``distilkit sweep FILE --status``, ``--wait``; :mod:`distilkit.sweep.slurm`
submits them).

What ran where is kept in ``<output>/<sweep>/slurm/jobs.json``; :func:`status` reads it with ``squeue`` and
``scontrol`` (states of queued and recently ended jobs) and the runs' own ``summary.json`` (done). Slurm's accounting
(``sacct``, slurmdbd with a database) is not needed: a run is done exactly when its summary exists, and a job that
has left the queue without one has failed (its log's last line says why).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError


def _queue_states(ids: list[str]) -> dict[str, str]:
    """Job id -> state of the jobs ``squeue`` still lists (PENDING, RUNNING, ...), array tasks by ``N_i``."""
    if not ids or shutil.which("squeue") is None:
        return {}
    done = subprocess.run(["squeue", "-h", "-r", "-o", "%i|%T|%r", "-j", ",".join(sorted({i.split("_")[0]
                                                                                          for i in ids}))],
                          capture_output=True, text=True)
    out = {}
    for line in done.stdout.splitlines():
        parts = line.strip().split("|")
        if len(parts) == 3:
            out[parts[0]] = parts[1] + (f" ({parts[2]})" if parts[2] not in ("None", "") else "")
    return out


def _ended_state(job_id: str) -> str | None:
    """The state ``scontrol`` remembers of a job that left the queue (for MinJobAge), else None."""
    if shutil.which("scontrol") is None:
        return None
    done = subprocess.run(["scontrol", "show", "job", job_id], capture_output=True, text=True)
    match = re.search(r"JobState=(\S+)", done.stdout)
    return match.group(1) if match else None


def _last_line(path: str) -> str:
    try:
        lines = [ln for ln in Path(path).read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "(no log)"
    errors = [ln for ln in lines if "Error" in ln or "error:" in ln]
    return (errors or lines or ["(empty log)"])[-1].strip()


@dataclass
class TaskStatus:
    title: str
    state: str  # pending | running | done | failed
    job_id: str
    log: str
    detail: str = ""
    key: tuple[str, int, tuple[str, ...]] = ("", 0, ())  # the task's variant, seed and stages (Task.key)


def status(run: Any) -> list[TaskStatus]:
    """One line per submitted task, newest submission of each task first: done (its summary exists), pending or
    running (``squeue``), else failed (the job left the queue without finishing the run)."""
    record = run.root / "slurm" / "jobs.json"
    if not record.is_file():
        raise DistilkitError(f"no Slurm jobs recorded for sweep {run.sweep.name} under {run.root} (submit with "
                             "--launcher slurm first)")
    latest: dict[tuple[str, int, tuple[str, ...]], dict[str, Any]] = {}
    for item in json.loads(record.read_text(encoding="utf-8")):
        latest[item["variant"], item["seed"], tuple(item["stages"])] = item
    queued = _queue_states([i["job_id"] for i in latest.values()])
    out = []
    for (variant, seed, stages), item in latest.items():
        task = run.task(variant, seed, stages)
        if run.finished(task):
            out.append(TaskStatus(item["title"], "done", item["job_id"], item["log"], key=task.key))
            continue
        state = queued.get(item["job_id"])
        if state is not None:
            word = "running" if state.startswith(("RUNNING", "COMPLETING")) else "pending"
            out.append(TaskStatus(item["title"], word, item["job_id"], item["log"], state, task.key))
            continue
        ended = _ended_state(item["job_id"]) or "left the queue"
        if item["after"] and not Path(item["log"]).is_file():  # cancelled by --kill-on-invalid-dep
            why = f"never ran: the upstream job {', '.join(item['after'])} did not finish"
        else:
            why = _last_line(item["log"])
        out.append(TaskStatus(item["title"], "failed", item["job_id"], item["log"], f"{ended}: {why}", task.key))
    return out


def wait(run: Any, console: Any, poll: float = 5.0, quiet: bool = False) -> list[TaskStatus]:
    """Show the jobs' progress until none is pending or running; the final states."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn(f"[cyan]sweep[/] {run.sweep.name} on Slurm"), BarColumn(), MofNCompleteColumn(),
                  TextColumn("{task.fields[states]}"), TimeElapsedColumn(), console=console,
                  disable=quiet) as progress:
        bar = None
        while True:
            states = status(run)
            counts = {s: sum(t.state == s for t in states) for s in ("pending", "running", "done", "failed")}
            text = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
            if bar is None:
                bar = progress.add_task("jobs", total=len(states), states=text)
            progress.update(bar, completed=counts["done"] + counts["failed"], states=text)
            if not counts["pending"] and not counts["running"]:
                return states
            time.sleep(poll)


__all__ = ["TaskStatus", "status", "wait"]
