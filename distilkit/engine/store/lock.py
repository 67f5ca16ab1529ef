"""One writer per stage run: two processes that would train the same stage (two ``distilkit run`` on one
output folder, the jobs of a sweep that share a teacher, a cluster's array tasks on a shared folder) take
turns instead of interleaving checkpoints. The lock is an ``flock`` on ``<output>/<recipe>/.locks/<run>.lock``
held while a stage is trained (or replaced by ``--rerun``); the kernel releases it when its process ends, so a
killed run leaves no stale lock. A process that finds the lock taken waits (and then reuses the finished
stage) or, with ``wait=False``, stops with :class:`~distilkit.errors.RunLockedError` naming the holder.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from pathlib import Path
from typing import Callable, Iterator

from distilkit.errors import RunLockedError


def lock_path(root: Path, run_name: str) -> Path:
    """The lock file of the stage run folder ``root/run_name``."""
    return root / ".locks" / f"{run_name}.lock"


@contextlib.contextmanager
def stage_lock(path: Path, wait: bool = True, on_wait: Callable[[str], None] | None = None,
               poll: float = 0.5) -> Iterator[None]:
    """Hold the lock file ``path`` for the duration. When another process holds it: with ``wait``, call
    ``on_wait(holder)`` once and wait for it; else raise :class:`RunLockedError` naming the holder."""
    try:
        import fcntl
    except ImportError:  # no flock on this platform: run unlocked
        yield
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        told = False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                holder = path.read_text(encoding="utf-8", errors="replace").strip() or "unknown process"
                what = path.name[: -len(".lock")]
                if not wait:
                    raise RunLockedError(f"{path.parent.parent / what} is being trained by another distilkit run "
                                         f"({holder}); wait for it to finish or give this one another --output") from None
                if not told and on_wait is not None:
                    on_wait(holder)
                told = True
                time.sleep(poll)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}".encode())
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


__all__ = ["lock_path", "stage_lock"]
