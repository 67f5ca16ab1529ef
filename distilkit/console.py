"""A rich console that stays readable when output is not a terminal (CI logs, pipes), and a stage's
progress bar."""

from __future__ import annotations

import contextlib
import shutil
from typing import Any, Callable, Iterator


def make_console(quiet: bool = False, **kwargs: Any) -> Any:
    from rich.console import Console

    console = Console(quiet=quiet, **kwargs)
    if not console.is_terminal:
        console = Console(quiet=quiet, width=max(shutil.get_terminal_size((160, 24)).columns, 160), **kwargs)
    return console


@contextlib.contextmanager
def stage_progress(console: Any, name: str) -> Iterator[Callable[[int, int, dict[str, float]], None]]:
    """A rich progress bar for one stage: steps, it/s, ETA and the current loss terms."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    columns = [TextColumn(f"[bold cyan]{name}[/]"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
               TextColumn("{task.fields[terms]}")]
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(name, total=None, rate="", terms="")
        state = {"t0": None, "s0": 0}

        def on_step(step: int, total: int, values: dict[str, float]) -> None:
            import time

            now = time.perf_counter()
            if state["t0"] is None:
                state["t0"], state["s0"] = now, step - 1
            done = step - state["s0"]
            rate = done / max(now - state["t0"], 1e-9)
            terms = " ".join(f"{k}={v:.3g}" for k, v in values.items())
            progress.update(task, completed=step, total=total, rate=f"{rate:.2f} it/s", terms=terms)

        yield on_step


@contextlib.contextmanager
def progress_bar(console: Any, what: str) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar for a loop over files: ``advance(done, total)``; count, elapsed time and ETA."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    with Progress(TextColumn(f"[cyan]{what}[/]"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("ETA"), TimeRemainingColumn(), console=console, transient=False) as progress:
        task = progress.add_task(what, total=None)
        yield lambda done, total: progress.update(task, completed=done, total=total)
