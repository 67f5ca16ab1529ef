"""Where a sweep run on this machine stands (``distilkit sweep FILE --status`` without Slurm jobs), read from its
output folder alone, so that another terminal can ask while ``distilkit sweep`` runs in the background (``nohup``,
``tmux``): each run is done (its ``summary.json`` says finished), running (a process holds its stage lock),
stopped (a checkpoint but no summary and no process: the next ``distilkit sweep`` resumes it) or waiting; and when
the rest should end at the pace of the runs finished so far. Torch-free."""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

MARKS = {"done": "✓", "running": "▶", "stopped": "‖", "waiting": "·"}


@dataclass
class RunState:
    variant: str
    seed: int
    state: str  # done | running | stopped | waiting
    finished_at: float | None = None  # a done run's end (seconds since the epoch)
    seconds: float | None = None  # a done run's own training time (its summary's train_seconds)


def locked(path: Path) -> bool:
    """Whether a process holds the ``flock`` on ``path`` (asked without taking it for longer than the asking)."""
    try:
        import fcntl
    except ImportError:  # no flock here: no run is known to be running
        return False
    if not path.is_file():
        return False
    fd = os.open(path, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def run_state(run_dir: Path) -> tuple[str, float | None]:
    """(state, the end of a done run) of one run folder."""
    state, at, _ = run_info(run_dir)
    return state, at


def run_info(run_dir: Path) -> tuple[str, float | None, float | None]:
    """(state, the end of a done run, its training seconds) of one run folder."""
    try:
        summary = json.loads((run_dir / "summary.json").read_text())
    except (OSError, ValueError):
        summary = None
    if summary is not None and summary.get("status") == "finished":
        at, took = summary.get("finished_at"), summary.get("train_seconds")
        took = float(took) if isinstance(took, (int, float)) else None
        try:
            return ("done", datetime.fromisoformat(at).timestamp() if at else (run_dir / "summary.json").stat().st_mtime,
                    took)
        except ValueError:
            return "done", (run_dir / "summary.json").stat().st_mtime, took
    if locked(run_dir.parent / ".locks" / f"{run_dir.name}.lock"):
        return "running", None, None
    if (run_dir / "checkpoints" / "last.pt").is_file():
        return "stopped", None, None
    return "waiting", None, None


def states(run: Any) -> list[RunState]:
    """Every variant run of the sweep (``run``: a :class:`~distilkit.sweep.runner.SweepRun`) at every seed."""
    out = []
    for seed in run.seeds:
        for variant in run.sweep.recipes:
            out.append(RunState(variant, seed, *run_info(run.pipes[variant, seed].run_dir(variant))))
    return out


def pace(ends: list[float], last: int = 20, seconds: list[float | None] | None = None) -> float | None:
    """Seconds per finished run, wall clock, over the last ``last`` ends (None from fewer than two).

    ``seconds`` (each end's run's own training time, in the same order as ``ends``) leaves out the time the sweep
    was not running: while it runs, the run that ends a gap between two ends was running through that gap, so a gap
    counts at most 1.5 times that run's training time (the rest is a stop, or a machine given back between
    sessions), where the plain span would spread a pause of hours over the last runs."""
    order = sorted(range(len(ends)), key=lambda i: ends[i])[-last:]
    if len(order) < 2 or ends[order[-1]] <= ends[order[0]]:
        return None
    busy = 0.0
    for before, after in zip(order, order[1:]):
        gap, took = ends[after] - ends[before], seconds[after] if seconds is not None else None
        busy += gap if took is None else min(gap, 1.5 * took)
    return busy / (len(order) - 1) if busy > 0 else None


def summary_line(name: str, found: list[RunState], now: float | None = None) -> str:
    """``sweep NAME: 120 of 264 runs done, 2 running, 1 stopped, 141 waiting; about 2 h 25 min more at the pace of
    the last 20 (55 s a run), if the sweep runs``."""
    from distilkit.sweep.processes import span

    count = {s: sum(r.state == s for r in found) for s in MARKS}
    text = (f"sweep {name}: {count['done']} of {len(found)} runs done, {count['running']} running, "
            f"{count['stopped']} stopped (resumed by the next `distilkit sweep`), {count['waiting']} waiting")
    left = len(found) - count["done"]
    finished = [r for r in found if r.finished_at is not None]
    each = pace([r.finished_at for r in finished], seconds=[r.seconds for r in finished])
    if left and each is not None:
        recent = min(20, count["done"])
        idle = (now or time.time()) - max(r.finished_at for r in found if r.finished_at is not None)
        text += (f"; about {span(each * left)} more at the pace of the last {recent} ({span(each)} a run)"
                 + ("" if count["running"] else ", once the sweep runs again")
                 + (f"; the last run ended {span(idle)} ago" if idle > 3 * each else ""))
    return text


def table(found: list[RunState], seeds: list[int]) -> Any:
    """A rich table: one row per variant, one column per seed, each run's mark."""
    from rich.table import Table

    grid = Table(title=" ".join(f"{m} {s}" for s, m in MARKS.items()), title_justify="left")
    grid.add_column("variant")
    for seed in seeds:
        grid.add_column(str(seed), justify="center")
    grid.add_column("done", justify="right")
    by = {(r.variant, r.seed): r for r in found}
    for variant in dict.fromkeys(r.variant for r in found):
        row = [by[variant, s] for s in seeds]
        grid.add_row(variant, *(MARKS[r.state] for r in row), f"{sum(r.state == 'done' for r in row)}/{len(row)}")
    return grid


def show(run: Any) -> list[RunState]:
    """Print the sweep's line and table on its console; return the states."""
    found = states(run)
    run.results_console.print(summary_line(run.sweep.name, found), highlight=False)
    run.results_console.print(table(found, run.seeds))
    return found


__all__ = ["MARKS", "RunState", "locked", "pace", "run_info", "run_state", "show", "states", "summary_line", "table"]
