"""One writer per output folder: two ``distilkit run`` processes on the same recipe output would interleave
checkpoints and logs, so the second one stops with a clear message instead. The lock is an ``flock`` on
``<output>/<recipe>/.distilkit.lock``, released by the kernel when its process ends (a killed run leaves no stale lock)."""

from __future__ import annotations

import contextlib
import os
import socket
import time
from pathlib import Path
from typing import Iterator

from distilkit.errors import RunLockedError


@contextlib.contextmanager
def run_lock(folder: Path) -> Iterator[None]:
    """Hold the folder's lock for the duration; raise :class:`RunLockedError` naming the holder when it is taken."""
    try:
        import fcntl
    except ImportError:  # no flock on this platform: run unlocked
        yield
        return
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / ".distilkit.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = path.read_text(encoding="utf-8", errors="replace").strip() or "unknown process"
            raise RunLockedError(f"{folder} is in use by another distilkit run ({holder}); wait for it to finish "
                                 "or give this one another --output") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}, since {time.strftime('%Y-%m-%d %H:%M:%S')}".encode())
        try:
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


__all__ = ["run_lock"]
