"""Stopping a run on request without losing its work: SIGTERM (a scheduler's, or a sweep's on its own way out) asks
the training loop to finish the step it is in, write ``last.pt`` and stop; a run started by a sweep also stops when
that sweep's process is gone (killed outright), so no run is left training without its parent. A second SIGTERM
stops at once (the last checkpoint is kept either way)."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

PARENT_ENV = "DISTILKIT_PARENT_PID"  # set by `distilkit sweep` for the runs it starts
_requested = threading.Event()


def requested() -> bool:
    """Whether this process was asked to stop (the loop checks after every step)."""
    return _requested.is_set()


def request() -> None:
    _requested.set()


def _on_term(signum: int, frame: Any) -> None:
    if _requested.is_set():  # asked twice: now
        raise KeyboardInterrupt
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
