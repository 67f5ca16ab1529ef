"""Stopping a run on request without losing its work: SIGTERM (a scheduler's, or a sweep's on its own way out) asks
the training loop to finish the step it is in, write ``last.pt`` and stop; a run started by a sweep also stops when
that sweep's process is gone (killed outright), so no run is left training without its parent. A second SIGTERM
stops at once (the last checkpoint is kept either way), unless it comes within 2 s of the first: Slurm's ``scancel
--signal=TERM --full`` delivers one signal more than once."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

PARENT_ENV = "DISTILKIT_PARENT_PID"  # set by `distilkit sweep` for the runs it starts
DUPLICATE_S = 2.0  # a second SIGTERM sooner than this after the first is the same signal delivered twice
_requested = threading.Event()


def requested() -> bool:
    """Whether this process was asked to stop (the loop checks after every step)."""
    return _requested.is_set()


def request() -> None:
    _requested.set()


_first: list[float] = []  # when the first SIGTERM came


def _on_term(signum: int, frame: Any) -> None:
    import time

    if _requested.is_set():  # asked twice: now — unless it is one signal delivered twice (a scheduler's, to every
        if _first and time.monotonic() - _first[0] < DUPLICATE_S:  # process of a job and again to its shell)
            return
        raise KeyboardInterrupt
    _first.append(time.monotonic())
    _requested.set()


def _watch_parent(pid: int, every: float) -> None:
    while not _requested.wait(every):
        if os.getppid() != pid:  # re-parented: the sweep that started this run is gone
            _requested.set()


def install(every: float = 1.0) -> None:
    """In ``distilkit run``: SIGTERM stops after the current step (with its checkpoint written); when started by a
    sweep (``DISTILKIT_PARENT_PID``), the run stops the same way once that process has died."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _on_term)
    parent = os.environ.get(PARENT_ENV)
    if parent and parent.isdigit():
        if os.getppid() != int(parent):  # the parent died before this process got here
            _requested.set()
        threading.Thread(target=_watch_parent, args=(int(parent), every), daemon=True,
                         name="distilkit-parent-watch").start()


__all__ = ["PARENT_ENV", "install", "request", "requested"]
