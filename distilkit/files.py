"""Atomic file writes: a temp file beside the target, fsynced, renamed over it, the folder fsynced. Whatever writes a
run's files (the engine, the reports) writes through these, so a kill never leaves half a file."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable


def _fsync_dir(path: Path) -> None:
    """Make a rename durable: fsync the folder that holds it (a no-op where folders cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _file_mode() -> int:
    """The mode a newly created file gets under the process's umask (0644 under umask 022): what ``open`` would give,
    where ``mkstemp`` gives 0600."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write(path: Path, write: Callable[[BinaryIO], None]) -> None:
    """Let ``write`` fill a temp file beside ``path``, fsync it, rename it over ``path`` and fsync the folder (the
    temp file is removed if anything fails). The file gets the mode the umask gives new files (as ``open``'s)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, _file_mode())
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda f: f.write(text.encode("utf-8")))


def atomic_write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True) + "\n")


def atomic_torch_save(path: Path, obj: Any) -> None:
    import torch  # here, not at the top: the commands that only read and write text never load torch

    atomic_write(path, lambda f: torch.save(obj, f))


def cache_root() -> Path:
    """Where distilkit keeps what it can make again (generated samples, the components' catalogue):
    ``$DISTILKIT_CACHE``, default ``~/.cache/distilkit``."""
    return Path(os.environ.get("DISTILKIT_CACHE", Path.home() / ".cache" / "distilkit"))


__all__ = ["atomic_torch_save", "atomic_write", "atomic_write_json", "atomic_write_text", "cache_root"]
