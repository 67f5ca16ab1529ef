"""Checkpoints on disk: a stage's ``last.pt`` (everything to resume from; the one it replaces is kept as
``last.prev.pt``, the fallback if ``last.pt`` is ever unreadable) and ``best.pt`` (the student at its best
validation score), written atomically by the main process; and every checkpoint or weights file read, always with
``torch.load(weights_only=True)`` (no code from a file is executed), and loaded into a model by name and shape."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable

import torch

from distilkit.files import atomic_torch_save
from distilkit.errors import DataError


def _load_safely(path: Path) -> Any:
    if not path.is_file():
        raise DataError(f"{path}: checkpoint not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise DataError(f"{path}: not a readable checkpoint ({type(exc).__name__}: {exc})") from None


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True`` (no code from the file is executed)."""
    path = Path(path)
    ckpt = _load_safely(path)
    if not isinstance(ckpt, dict) or "student" not in ckpt:
        raise DataError(f"{path}: not a distilkit checkpoint (no 'student' weights)")
    return ckpt


def read_state_dict(path: str | Path) -> dict[str, Any]:
    """A state dict from a distilkit checkpoint (``student``) or a weights file (the dict itself, or under
    ``state_dict`` / ``model``), loaded with ``weights_only=True``."""
    path = Path(path).expanduser()
    obj = _load_safely(path)
    if isinstance(obj, dict):
        for key in ("student", "state_dict", "model"):
            if isinstance(obj.get(key), dict):
                obj = obj[key]
                break
    if not isinstance(obj, dict) or not obj or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise DataError(f"{path}: no state dict found (expected a distilkit checkpoint or a dict of tensors, "
                        f"possibly under 'state_dict' or 'model')")
    return obj


def load_weights(model: torch.nn.Module, weights: dict[str, Any], strict: bool, source: str) -> list[str]:
    """Load ``weights`` into ``model``; strict: all must fit, else the ones that fit by name and shape.
    Returns what was left out (names), for the log. A misfit under ``strict`` is a one-line DataError."""
    own = model.state_dict()
    misfit = [k for k, v in weights.items() if k in own and tuple(own[k].shape) != tuple(v.shape)]
    missing = [k for k in own if k not in weights]
    unexpected = [k for k in weights if k not in own]
    if strict and (misfit or missing or unexpected):
        parts = [f"{len(x)} {what} (e.g. {x[0]})" for x, what in ((missing, "missing"), (unexpected, "unexpected"),
                                                                   (misfit, "of another shape")) if x]
        raise DataError(f"{source}: weights do not fit {type(model).__name__}: {'; '.join(parts)} "
                        f"(set strict: false to load the ones that fit)")
    fit = {k: v for k, v in weights.items() if k in own and k not in misfit}
    model.load_state_dict(fit, strict=False)
    return sorted(missing + misfit)



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


__all__ = ["Checkpoints", "load_checkpoint", "load_weights", "read_state_dict"]
