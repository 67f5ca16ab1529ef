"""A rich console that stays readable when output is not a terminal (CI logs, pipes), and a stage's
progress bar."""

from __future__ import annotations

import contextlib
import os
import shutil
from typing import Any, Callable, Iterator


def make_console(quiet: bool = False, **kwargs: Any) -> Any:
    """A console as wide as the terminal; off a terminal (a pipe, a CI log) 160 columns or more, unless ``COLUMNS``
    says how wide (rich reads it)."""
    from rich.console import Console

    console = Console(quiet=quiet, **kwargs)
    if not console.is_terminal and not os.environ.get("COLUMNS", "").isdigit():
        console = Console(quiet=quiet, width=max(shutil.get_terminal_size((160, 24)).columns, 160), **kwargs)
    return console


class StageBar:
    """What :func:`stage_progress` yields: called with (step, total, loss terms) after each step; ``evaluation(done,
    total)`` shows an evaluation's progress on the same line (None, None: it ended)."""

    def __init__(self, progress: Any, task: Any) -> None:
        import time

        self.progress, self.task, self.clock = progress, task, time.perf_counter
        self.t0: float | None = None
        self.s0 = 0

    def __call__(self, step: int, total: int, values: dict[str, float]) -> None:
        now = self.clock()
        if self.t0 is None:  # the first step after a (re)start times nothing yet: no rate until the second
            self.t0, self.s0 = now, step
            rate = ""
        else:
            rate = f"{(step - self.s0) / max(now - self.t0, 1e-9):.1f} it/s"
        self.rate = rate
        terms = " ".join(f"{k}={v:.3g}" for k, v in values.items())
        self.progress.update(self.task, completed=step, total=total, rate=rate, terms=terms)

    def evaluation(self, done: int | None, total: int | None) -> None:
        """An evaluation's progress where the rate is shown (the rate again when it ends)."""
        self.progress.update(self.task, rate=getattr(self, "rate", "") if done is None else f"eval {done}/{total}")


def _columns(name: str, *extra: Any) -> list[Any]:
    """Progress columns that keep their counts whole in a narrow terminal: the label and the free text give way
    (folded, then cut with an ellipsis) before the count and the times do."""
    from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
    from rich.table import Column

    return [TextColumn(name, table_column=Column(overflow="ellipsis", no_wrap=True, max_width=20)),
            BarColumn(bar_width=None, table_column=Column(ratio=1, min_width=6)),
            MofNCompleteColumn(table_column=Column(no_wrap=True)), *extra,
            TimeElapsedColumn(table_column=Column(no_wrap=True)), TextColumn("ETA"),
            TimeRemainingColumn(table_column=Column(no_wrap=True))]


@contextlib.contextmanager
def stage_progress(console: Any, name: str) -> Iterator[StageBar]:
    """A rich progress bar for one stage: steps, it/s, elapsed time, ETA and the current loss terms (or an
    evaluation's progress)."""
    from rich.progress import Progress, TextColumn
    from rich.table import Column

    columns = _columns(f"[bold cyan]{name}[/]", TextColumn("{task.fields[rate]}", table_column=Column(no_wrap=True)))
    columns.append(TextColumn("{task.fields[terms]}", table_column=Column(ratio=1, no_wrap=True, overflow="ellipsis")))
    with Progress(*columns, console=console, transient=False, expand=True) as progress:
        yield StageBar(progress, progress.add_task(name, total=None, rate="", terms=""))


@contextlib.contextmanager
def progress_bar(console: Any, what: str, transient: bool = False) -> Iterator[Callable[[int, int], None]]:
    """A rich progress bar for a loop over files or samples: ``advance(done, total)``; count, elapsed time and ETA
    (``transient``: gone when it ends)."""
    from rich.progress import Progress

    with Progress(*_columns(f"[cyan]{what}[/]"), console=console, transient=transient) as progress:
        task = progress.add_task(what, total=None)
        yield lambda done, total: progress.update(task, completed=done, total=total)
