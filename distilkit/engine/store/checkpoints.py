"""A stage's checkpoints on disk: ``last.pt`` (everything to resume from; the one it replaces is kept as
``last.prev.pt``, the fallback if ``last.pt`` is ever unreadable) and ``best.pt`` (the student at its best
validation score), written atomically by the main process and read back safely (:mod:`distilkit.weights`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

from distilkit.errors import DataError
from distilkit.files import atomic_torch_save
from distilkit.weights import folder_hint, load_checkpoint


class Checkpoints:
    def __init__(self, folder: Path, writer: bool = True) -> None:
        self.folder, self.writer = folder, writer
        self.saved_step: int | None = None  # the step of last.pt (None: none written or found yet)

    def write_last(self, state: dict[str, Any], step: int) -> None:
        if not self.writer:
            return
        last = self.folder / "last.pt"
        if last.is_file():
            os.replace(last, self.folder / "last.prev.pt")
        atomic_torch_save(last, state)
        self.saved_step = step

    def write_best(self, state: dict[str, Any]) -> None:
        if self.writer:
            atomic_torch_save(self.folder / "best.pt", state)

    def resume(self, on_unreadable: Callable[[Exception, Path], None]) -> dict[str, Any] | None:
        """The newest readable of ``last.pt`` and ``last.prev.pt`` (an unreadable one is reported to
        ``on_unreadable``), or None to start from the beginning."""
        for name in ("last.pt", "last.prev.pt"):
            path = self.folder / name
            if not path.is_file():
                continue
            try:
                ckpt = load_checkpoint(path)
            except DataError as exc:
                on_unreadable(exc, path)
                continue
            self.saved_step = int(ckpt["step"])
            return ckpt
        return None

    def kept(self) -> str:
        """What a stopped run leaves to resume from, as it is: the last checkpoint and its step, or none."""
        if self.saved_step is None:
            return "no checkpoint had been written yet (a new run starts from step 0)"
        return f"the last checkpoint ({self.folder / 'last.pt'}, step {self.saved_step}) is kept"


def checkpoint_file(source: str | Path, which: str = "best") -> Path:
    """The checkpoint file of ``source``: a file as it is, or a stage run folder's ``checkpoints/<which>.pt``
    (``which="any"``: best, else last); a DataError in one line otherwise, a folder's naming what it holds."""
    path = Path(source).expanduser()
    if path.is_dir():
        names = ("best.pt", "last.pt") if which == "any" else (f"{which}.pt",)
        for name in names:
            if (path / "checkpoints" / name).is_file():
                return path / "checkpoints" / name
        wanted = "checkpoints/" + " or checkpoints/".join(names)
        if (path / "checkpoints").is_dir() or (path / "summary.json").is_file():
            raise DataError(f"{path}: no {wanted} in this stage's run folder; {folder_hint(path)}")
        raise DataError(f"{path}: not a stage's run folder: no {wanted} in it (a stage's run folder "
                        f"runs/<recipe>/<stage>-<hash> holds {'it' if len(names) == 1 else 'them'}); "
                        f"{folder_hint(path)}")
    if not path.is_file():
        raise DataError(f"{path}: no such file or folder")
    return path


__all__ = ["Checkpoints", "checkpoint_file"]
