"""Safe checkpoint loading, weights that fit a model, and the random state of a run (atomic writes:
:mod:`distilkit.files`)."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import numpy as np
import torch

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


def rng_state() -> dict[str, Any]:
    """Every generator a run draws from: torch (CPU and each CUDA device), numpy and Python."""
    np_state = np.random.get_state()
    cuda = torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []
    return {
        "cuda": cuda,
        "torch": torch.get_rng_state(),
        "numpy": [np_state[0], torch.from_numpy(np_state[1].astype(np.int64)), int(np_state[2]), int(np_state[3]),
                  float(np_state[4])],
        "python": list(random.getstate()[1]),
        "python_version": random.getstate()[0],
    }


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    n = state["numpy"]
    np.random.set_state((n[0], n[1].numpy().astype(np.uint32), n[2], n[3], n[4]))
    random.setstate((state["python_version"], tuple(state["python"]), None))
    cuda = state.get("cuda") or []
    if cuda and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)
