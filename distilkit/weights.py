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


_ZIP = b"PK\x03\x04"  # torch.save's format since 1.6: a zip archive, its directory at the end
_LEGACY = b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19"  # the legacy format's pickled magic number


def _cut_short(path: Path, exc: Exception) -> str | None:
    """"it is not a complete PyTorch file (N bytes): ..." where that is what is wrong with ``path`` (torch failed
    reading it with ``exc``): empty, a zip archive without its end (the directory a zip keeps there), the legacy
    format ending before its data does, or the first bytes of either; None for any other file."""
    import zipfile

    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(len(_LEGACY))
    text = str(exc).lower()
    if size == 0:
        why = "the file is empty"
    elif size < len(_LEGACY) and (_ZIP.startswith(head) or _LEGACY.startswith(head) or head.startswith(_ZIP)):
        why = "it ends within the first bytes of one"
    elif head.startswith(_ZIP) and not zipfile.is_zipfile(path):
        why = "the end of its zip archive is missing"
    elif head.startswith(_LEGACY) and (isinstance(exc, EOFError) or type(exc).__name__ == "error"  # struct.error
                                       or "eof" in text or "truncated" in text):
        why = "it ends before its data does"
    else:
        return None
    return f"it is not a complete PyTorch file ({size} bytes): {why} (copied or downloaded only in part?)"


def _numpy_file(path: Path) -> str:
    """"a NumPy array file (.npy: float32, shape (5, 3))", its header read without unpickling anything."""
    from numpy.lib import format as npy

    try:
        with open(path, "rb") as f:
            version = npy.read_magic(f)
            read = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, _, dtype = read(f)  # the header's literal alone, nothing unpickled
        return f"a NumPy array file (.npy: {dtype}, shape {tuple(shape)})"
    except Exception:
        return "a NumPy array file (.npy)"


def _zip_members(path: Path) -> list[str]:
    import zipfile

    try:
        with zipfile.ZipFile(path) as z:
            return z.namelist()
    except Exception:
        return []


def _other_format(path: Path) -> str | None:
    """What a file torch could not read is, where its first bytes say (a text file, a NumPy array or archive, a
    safetensors or HDF5 file, a zip archive that is not torch.save's); None for anything else."""
    with open(path, "rb") as f:
        head = f.read(4096)
    if head.startswith(b"\x93NUMPY"):
        return _numpy_file(path)
    if head.startswith(_ZIP):
        members = _zip_members(path)
        if members and all(m.endswith(".npy") for m in members):
            shown = [m[:-4] for m in members[:6]] + ([f"{len(members) - 6} more"] if len(members) > 6 else [])
            return f"a NumPy archive (.npz: {', '.join(shown)})"
        if members and not any(m.endswith("data.pkl") for m in members):
            return f"a zip archive without torch.save's data.pkl ({len(members)} member{'s' * (len(members) != 1)})"
        return None
    if head.startswith(b"\x89HDF\r\n\x1a\n"):
        return "an HDF5 file (Keras or TensorFlow weights?)"
    if len(head) > 10 and head[8:10] == b'{"':
        return "a safetensors file (read it with safetensors.torch.load_file and torch.save its dict)"
    text = _text(head)
    if text is not None and text.strip():
        first = next(line.strip() for line in text.splitlines() if line.strip())
        return f"a text file (first line: {first[:60] + ('...' if len(first) > 60 else '')!r})"
    return None


def _text(head: bytes) -> str | None:
    """A file's first bytes as UTF-8 text (a character the read cut at its end left out), None where they are not
    text (a NUL byte, or bytes UTF-8 has no character for)."""
    if b"\x00" in head:
        return None
    try:
        return head.decode("utf-8")
    except UnicodeDecodeError as exc:
        return head[:exc.start].decode("utf-8") if exc.start >= len(head) - 3 else None


CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt")


def _some(names: list[str], limit: int = 4) -> str:
    return ", ".join(names[:limit]) + (f" and {len(names) - limit} more" if len(names) > limit else "")


def folder_hint(path: Path) -> str:
    """What a folder given where a checkpoint is read holds that was perhaps meant, in words: its checkpoint files
    (a run's ``checkpoints/best.pt`` and ``last.pt`` among them), else the stage runs under it, else neither."""
    files = sorted(str(f.relative_to(path)) for f in (*path.iterdir(), *path.glob("checkpoints/*"))
                   if f.suffix in CHECKPOINT_SUFFIXES and f.is_file())
    if files:
        return f"it holds {_some(files)}: give {'that file' if len(files) == 1 else 'one of them'}"
    runs = sorted(d.name for d in path.iterdir() if (d / "checkpoints").is_dir() or (d / "summary.json").is_file())
    if runs:
        return f"it holds stage runs: {_some(runs)}: give {'it' if len(runs) == 1 else 'one of them'}"
    return f"it holds no checkpoint file ({', '.join(CHECKPOINT_SUFFIXES)}) and no stage run"


def not_a_file(path: Path) -> str | None:
    """One line where ``path``, given as a checkpoint or weights file, is not a file (missing, or a folder: what it
    holds); None for a file."""
    if path.is_file():
        return None
    if path.is_dir():
        return f"{path}: not a readable checkpoint: it is a folder, not a file; {folder_hint(path)}"
    return f"{path}: no such file"


def _globals_in(path: Path) -> list[str]:
    """The Python names (module.qualname) the pickle of a torch.save zip file refers to beyond torch's own and the
    builtin containers, in order, once each ([] where it cannot be read). Read from the pickle's opcodes, not run:
    ``GLOBAL`` (protocol 2, torch's), ``STACK_GLOBAL`` (protocol 4) and protocol 2's spelling of a nested class,
    ``getattr(module.Outer, "Inner")``, which torch's message names only as ``getattr``."""
    import pickletools
    import zipfile

    plain = ("torch.", "collections.OrderedDict", "builtins.", "_codecs.", "__builtin__.")
    try:
        with zipfile.ZipFile(path) as z:
            data = z.read(next(n for n in z.namelist() if n.endswith("data.pkl")))
        names: list[str] = []
        pushed: list[str | None] = []  # what the latest opcodes pushed: a string or name, else None
        memo: dict[int, str | None] = {}
        for op, arg, _ in pickletools.genops(data):
            if op.name == "GLOBAL":
                pushed.append(str(arg).replace(" ", "."))
                names.append(str(pushed[-1]))
            elif op.name == "STACK_GLOBAL" and len(pushed) >= 2 and None not in pushed[-2:]:
                pushed[-2:] = [f"{pushed[-2]}.{pushed[-1]}"]
                names.append(str(pushed[-1]))
            elif isinstance(arg, str) and ("UNICODE" in op.name or "STRING" in op.name):
                pushed.append(arg)
            elif op.name == "MEMOIZE":
                memo[len(memo)] = pushed[-1] if pushed else None
            elif op.name in ("PUT", "BINPUT", "LONG_BINPUT"):
                memo[int(arg)] = pushed[-1] if pushed else None
            elif op.name in ("GET", "BINGET", "LONG_BINGET"):
                pushed.append(memo.get(int(arg)))
            elif op.name == "TUPLE2" and len(pushed) >= 3 and None not in pushed[-2:] \
                    and pushed[-3] in ("builtins.getattr", "__builtin__.getattr"):
                if names and names[-1] == pushed[-2]:  # Outer named as getattr's argument: Outer.Inner instead
                    names.pop()
                names.append(f"{pushed[-2]}.{pushed[-1]}")  # getattr(Outer, "Inner")
                pushed.append(None)
            else:
                pushed.append(None)
            pushed = pushed[-3:]
    except Exception:
        return []
    return list(dict.fromkeys(n for n in names if not n.startswith(plain)))


def _reason(exc: Exception, path: Path) -> str:
    """What is wrong with a file torch could not read as plain weights, in one line: the Python names it holds that
    only running code from it could rebuild (module.qualname, without torch's advice to load it with
    ``weights_only=False``, which would run that code), or that it is not a complete PyTorch file (empty, or cut
    short: its size), or torch's own first sentence."""
    import re

    short = _cut_short(path, exc)
    if short is not None:
        return short
    other = _other_format(path)
    if other is not None:
        return f"it is {other}, not a file torch.save wrote"
    text = str(exc)
    if text.startswith("Weights only load failed"):
        names = _globals_in(path) or list(dict.fromkeys(re.findall(r"GLOBAL ([A-Za-z_][\w.]*)", text)))
        if names:
            if len(names) > 4:
                names = [*names[:3], f"{len(names) - 3} more"]
            held = ", ".join(names[:-1]) + " and " + names[-1] if len(names) > 1 else names[0]
            return (f"it holds {held}, which plain weights (tensors, numbers, strings, lists, dicts) never do and "
                    "only code from the file could rebuild; distilkit never runs code from a file (if you trust "
                    "this one, load it in Python and torch.save its state dict alone)")
        paragraphs = [p.strip() for p in text.split("\n\n") if p.strip()]
        detail = next((p for p in paragraphs[1:] if "weights_only" not in p and not p.startswith("Check the")), "")
        detail = detail.replace("WeightsUnpickler error:", "").strip()
        return (f"not loadable as plain weights{f': {_sentence(detail)}' if detail else ''}; distilkit reads "
                "weights only and never runs code from a file")
    return f"{type(exc).__name__}: {_sentence(text) or 'no message'}"


def _sentence(text: str, limit: int = 300) -> str:
    """The first sentence of ``text``'s first line, cut at a word (with "...") where it runs past ``limit``."""
    first = text.strip().split("\n")[0].strip()
    end = first.find(". ")
    first = first[:end + 1] if end >= 0 else first
    if len(first) <= limit:
        return first
    return first[:limit].rsplit(" ", 1)[0] + " ..."


def _load_safely(path: Path) -> Any:
    problem = not_a_file(path)
    if problem:
        raise DataError(problem)
    try:
        try:  # memory-mapped: a tensor is read only when used (validate reads shapes alone)
            return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        except RuntimeError as exc:
            if "mmap" not in str(exc):
                raise
            return torch.load(path, map_location="cpu", weights_only=True)  # the legacy (non-zip) format
    except Exception as exc:
        raise DataError(f"{path}: not a readable checkpoint: {_reason(exc, path)}") from None


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
    """The first tensor of ``weights`` (of the keys in ``only``, if given) holding values no trained model has,
    named (as the file spells it too) with how many: a floating-point tensor with NaN or infinite values, or a
    BatchNorm ``running_var`` with negative ones (a variance is never negative; one of 0 is a channel that was
    constant in training, e.g. a dead one, and is kept); None where every value is as it can be."""
    spell = spelling(weights)
    for key, value in weights.items():
        if only is not None and key not in only:
            continue
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            where = f"{key}{in_the_file(key, tuple(value.shape), spell)}"
            finite = torch.isfinite(value)
            if not bool(finite.all()):
                return f"{where} holds {int((~finite).sum()):,} NaN or infinite values of {value.numel():,}"
            if key.endswith("running_var") and bool((value < 0).any()):
                return (f"{where} (a BatchNorm running variance) holds {int((value < 0).sum()):,} negative values "
                        f"of {value.numel():,} (the lowest {float(value.min()):.4g}): not the statistics of a trained "
                        "model")
    return None


__all__ = ["ImportedWeights", "PartialWeights", "folder_hint", "in_the_file", "load_checkpoint", "load_weights",
           "mismatch", "not_a_file", "not_finite", "read_state_dict", "spelling", "under_prefix", "whole_problem"]
