"""Weights files read safely: every checkpoint or weights file is read with ``torch.load(weights_only=True)`` (no code
from a file is executed; a file that would need it gets one line saying so), and loaded into a model by name and
shape, with every key used or reported (a released checkpoint's names mapped by its adapter's importer:
:class:`ImportedWeights`, :class:`PartialWeights`). The engine's own checkpoints (``last.pt``, ``best.pt``) are
written by :mod:`distilkit.engine.store.checkpoints`."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any, Callable

import torch

from distilkit.errors import DataError


def _reason(exc: Exception) -> str:
    """What torch says is wrong with a file, without its advice to load it with ``weights_only=False`` (which would
    run code from an untrusted file)."""
    text = str(exc)
    if text.startswith("Weights only load failed"):
        paragraphs = [p.strip() for p in text.split("\n\n") if p.strip()]
        detail = next((p for p in paragraphs[1:] if "weights_only" not in p and not p.startswith("Check the")), "")
        detail = detail.replace("WeightsUnpickler error:", "").strip()
        return (f"not loadable as plain weights{f': {detail[:300]}' if detail else ''}; distilkit reads weights "
                "only and never runs code from a file")
    first = text.strip().split("\n")[0]
    return f"{type(exc).__name__}: {first[:300]}"


def _load_safely(path: Path) -> Any:
    if not path.is_file():
        raise DataError(f"{path}: checkpoint not found")
    try:
        try:  # memory-mapped: a tensor is read only when used (validate reads shapes alone)
            return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as exc:
            if "mmap" not in str(exc):
                raise
            return torch.load(path, map_location="cpu", weights_only=True)  # the legacy (non-zip) format
    except Exception as exc:
        raise DataError(f"{path}: not a readable checkpoint ({_reason(exc)})") from None


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


class ImportedWeights(dict):
    """A released file's weights under the model's names (an adapter's ``read_weights`` converted them): errors name
    a key as the model calls it and as the file spells it. ``spelled``: the file's key of each key it has;
    ``file_name(key, shape)``: how the file would spell a key of the model's (of that shape) that it lacks;
    ``ignored``: what the file held that is not the model's by design, said in the log (as :class:`PartialWeights`)."""

    def __init__(self, weights: dict[str, Any], spelled: dict[str, str],
                 file_name: Callable[[str, tuple[int, ...]], str], ignored: tuple[str, ...] = ()) -> None:
        super().__init__(weights)
        self.spelled, self.file_name, self.ignored = spelled, file_name, ignored


def _bare(prefix: str, key: str, shape: tuple[int, ...]) -> str:
    return key[len(prefix):] if key.startswith(prefix) else key


def under_prefix(weights: dict[str, Any], prefixes: tuple[str, ...], left_out: dict[str, str],
                 prefix: str = "net.") -> dict[str, Any]:
    """A release's state dict under the model's names: the keys that start with one of ``prefixes`` gain ``prefix``
    (the adapter's ``net.``); those that start with a key of ``left_out`` are what the release holds and the network
    does not, by design, dropped and said with the reason (``KEY.* (why)`` for a whole module). ``weights`` as they
    are when no key starts with ``prefixes`` (a distilkit checkpoint)."""
    if not any(k.startswith(prefixes) for k in weights):
        return weights
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    said: dict[str, None] = {}  # in order, once each
    for key, value in weights.items():
        drop = next((d for d in left_out if key.startswith(d)), None)
        if drop is not None:
            said[f"{drop + '*' if drop.endswith('.') else key} ({left_out[drop]})"] = None
            continue
        name = prefix + key if key.startswith(prefixes) else key
        out[name] = value
        spelled[name] = key
    return ImportedWeights(out, spelled, partial(_bare, prefix), tuple(said))


def spelling(weights: dict[str, Any]) -> Callable[[str, tuple[int, ...]], str] | None:
    """How the file behind ``weights`` spells a key of the model's (None: as the model does)."""
    if not isinstance(weights, ImportedWeights):
        return None
    return lambda key, shape: weights.spelled.get(key) or weights.file_name(key, shape)


def in_the_file(key: str, shape: tuple[int, ...], spell: Callable[[str, tuple[int, ...]], str] | None) -> str:
    """`` (in the file: NAME)`` where the file spells ``key`` otherwise, else ""."""
    spelled = spell(key, shape) if spell else key
    return "" if spelled == key else f" (in the file: {spelled})"


class PartialWeights(dict):
    """The weights of one part of a model, by design (a pretrained image backbone): every weight of the model under
    ``scope`` must be there (under ``strict``), the rest of the model keeps its initial weights. ``ignored``: what
    the file held that the model has no place for by design, said in the log (e.g. an ImageNet classifier)."""

    def __init__(self, weights: dict[str, Any], scope: str, ignored: tuple[str, ...] = ()) -> None:
        super().__init__(weights)
        self.scope, self.ignored = scope, ignored


def whole_problem(weights: dict[str, Any]) -> str | None:
    """Why ``weights`` cannot be a whole model (a teacher's): they are one part of it (:class:`PartialWeights`)."""
    scope = getattr(weights, "scope", "")
    if not scope:
        return None
    return (f"holds only {scope}* (a pretrained part of the model, e.g. an ImageNet backbone): a teacher's "
            "checkpoint must hold the whole model; start a student from it with `init: {checkpoint: ...}`")


def mismatch(own: dict[str, tuple[int, ...]], given: dict[str, tuple[int, ...]], strict: bool = True,
             scope: str = "", spell: Callable[[str, tuple[int, ...]], str] | None = None) -> str | None:
    """Every key of ``given`` (a file's shapes) that does not fit ``own`` (a model's), named: missing, unexpected and
    of another shape (with both shapes); None where they fit (not ``strict``: only keys of another shape count,
    missing and unexpected ones being left out by design). ``scope``: only the model's keys under it are expected
    (:class:`PartialWeights`). ``spell`` (:func:`spelling`): a key is also named as the file spells it."""
    scope = getattr(given, "scope", scope)
    misfit = [f"{k} {tuple(given[k])} (model: {tuple(own[k])}){in_the_file(k, given[k], spell)}" for k in given
              if k in own and given[k] != own[k]]
    missing = [k + in_the_file(k, own[k], spell) for k in own if k.startswith(scope) and k not in given] \
        if strict else []
    unexpected = [k + in_the_file(k, given[k], spell) for k in given if k not in own] if strict else []
    parts = [f"{len(keys)} {what}: {', '.join(keys)}" for keys, what in
             ((missing, "missing"), (unexpected, "unexpected"), (misfit, "of another shape")) if keys]
    return "; ".join(parts) or None


def load_weights(model: torch.nn.Module, weights: dict[str, Any], strict: bool, source: str) -> list[str]:
    """Load ``weights`` into ``model``; strict: all must fit, else the ones that fit by name and shape.
    Returns what was left out (names), for the log. A misfit under ``strict`` is a DataError naming every key.
    :class:`PartialWeights` load one part of the model (its ``scope``); what the file held beyond the model by
    design (``ignored``) is listed too, as ``ignored: ...``."""
    own = model.state_dict()
    scope = getattr(weights, "scope", "")
    problem = mismatch({k: tuple(v.shape) for k, v in own.items()}, {k: tuple(v.shape) for k, v in weights.items()},
                       strict, scope, spelling(weights))
    if strict and problem:
        raise DataError(f"{source}: weights do not fit {type(model).__name__}: {problem} (set strict: false to load "
                        "the ones that fit)")
    misfit = [k for k, v in weights.items() if k in own and tuple(own[k].shape) != tuple(v.shape)]
    missing = [k for k in own if k.startswith(scope) and k not in weights]
    fit = {k: v for k, v in weights.items() if k in own and k not in misfit}
    bad = not_finite(weights, fit)
    if bad:
        raise DataError(f"{source}: {bad}; refusing to load it")
    model.load_state_dict(fit, strict=False)
    return sorted(missing + misfit) + [f"ignored: {name}" for name in getattr(weights, "ignored", ())]


def not_finite(weights: dict[str, Any], only: Any = None) -> str | None:
    """The first floating-point tensor of ``weights`` (of the keys in ``only``, if given) holding NaN or infinite
    values, named (as the file spells it too) with how many; None where every value is finite."""
    spell = spelling(weights)
    for key, value in weights.items():
        if only is not None and key not in only:
            continue
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            finite = torch.isfinite(value)
            if not bool(finite.all()):
                return (f"{key}{in_the_file(key, tuple(value.shape), spell)} holds {int((~finite).sum()):,} NaN or "
                        f"infinite values of {value.numel():,}")
    return None


__all__ = ["ImportedWeights", "PartialWeights", "in_the_file", "load_checkpoint", "load_weights", "mismatch",
           "not_finite", "read_state_dict", "spelling", "under_prefix", "whole_problem"]
