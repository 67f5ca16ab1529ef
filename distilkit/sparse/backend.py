"""Which implementation computes a sparse convolution, chosen per call: ``DISTILKIT_SPARSE=auto|torch|spconv|
spconv-triton`` (``auto`` when unset), or :func:`using` in code, which wins over the variable.

* ``torch`` — :mod:`distilkit.sparse.function`: gather, GEMM and scatter-add in PyTorch, forward and backward on
  any device, the same bits in every process.
* ``spconv`` — spconv 2.x's ``indice_conv`` (its gather-GEMM-scatter, ``ConvAlgo.Native``) on distilkit's own
  neighbour maps. Forward and backward on CUDA (a ``spconv-cu1xx`` build); spconv's CPU build (``pip install
  spconv``) computes the forward only — its backward asks for CUDA — so it serves inference on the CPU and a step
  that needs gradients there is refused. spconv 2.3.8's CPU forward races when torch runs more than one thread (its
  own ``SubMConv3d`` gave outputs up to 0.27 apart over five calls on the same input with 2 threads, none apart with
  1; the same on distilkit's maps), so distilkit runs it with one thread.
* ``spconv-triton`` — spconv-Triton's ``indice_conv``, the same functions in Triton (NVIDIA and AMD GPUs; not on
  the CPU).
* ``auto`` — on CUDA the first of spconv (a CUDA build), spconv-triton, torch that imports; elsewhere torch.

The maps (which input row feeds which output row, per kernel offset) are distilkit's in every backend — only the
products and sums move — so the output rows, their order and the weights' layout (out, k0, k1, k2, in) are the same,
and a checkpoint moves between backends unchanged. spconv 1.x's reuse of a stored map of a smaller kernel K' runs
on every backend as what it is: a convolution of kernel K' whose weight is the first vol(K') slices of this kernel.

An explicitly requested backend that cannot run here is an error naming what is missing; it never falls back.
Under CUDA autocast spconv and spconv-Triton cast their inputs to float16 whatever autocast's dtype
(``custom_fwd(cast_inputs=torch.float16)`` in their ``functional.py``); the torch backend computes in autocast's
dtype and sums in float32. :func:`record` collects which backends ran (a stage's summary names them).
"""

from __future__ import annotations

import contextlib
import importlib
import os
from functools import cache
from typing import Any, Iterator

import torch
from torch import Tensor

from distilkit.errors import DistilkitError

ENV = "DISTILKIT_SPARSE"
CHOICES = ("auto", "torch", "spconv", "spconv-triton")
LIBRARIES = {"spconv": "spconv", "spconv-triton": "spconv_triton"}  # backend -> the module it imports
INSTALL = {"spconv": "pip install spconv-cu120 (a CUDA build; pip install spconv is the CPU build: forward only)",
           "spconv-triton": "pip install spconv-triton"}


class SparseBackendError(DistilkitError):
    """A requested sparse backend cannot run here (not installed, not for this device, no backward)."""


_override: list[str] = []  # :func:`using`'s choices, innermost last
_ran: list[set[str]] = []  # :func:`record`'s open collections


def requested() -> str:
    """The backend asked for: the innermost :func:`using`, else ``DISTILKIT_SPARSE``, else ``auto``."""
    if _override:
        return _override[-1]
    value = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if value not in CHOICES:
        raise SparseBackendError(f"{ENV}={value!r}: choose one of {', '.join(CHOICES)}")
    return value


@contextlib.contextmanager
def using(name: str) -> Iterator[None]:
    """Run the convolutions inside the block on backend ``name`` (one of :data:`CHOICES`), whatever the variable."""
    if name not in CHOICES:
        raise SparseBackendError(f"sparse backend {name!r}: choose one of {', '.join(CHOICES)}")
    _override.append(name)
    try:
        yield
    finally:
        _override.pop()


@contextlib.contextmanager
def record() -> Iterator[set[str]]:
    """The set of backends that computed a convolution while the block was open."""
    seen: set[str] = set()
    _ran.append(seen)
    try:
        yield seen
    finally:
        _ran.remove(seen)


@cache
def _library(name: str) -> tuple[Any, Any, bool] | str:
    """(its ``pytorch.functional`` module, ``ConvAlgo.Native``, whether it runs on CUDA) of a library backend, or why
    it does not import."""
    module = LIBRARIES[name]
    try:
        functional = importlib.import_module(f"{module}.pytorch.functional")
        algo = importlib.import_module(f"{module}.core").ConvAlgo.Native
    except Exception as exc:  # not installed, or a build that does not load against this torch
        return f"{module} does not import ({type(exc).__name__}: {exc}); {INSTALL[name]}"
    cuda = True
    if name == "spconv":
        try:
            cuda = not importlib.import_module("spconv.cppconstants").CPU_ONLY_BUILD
        except Exception:  # an older layout: assume a CUDA build and let the call say otherwise
            cuda = True
    return functional, algo, cuda


def problem(name: str, device_type: str) -> str | None:
    """Why backend ``name`` cannot compute on ``device_type`` here (None: it can)."""
    if name == "torch":
        return None
    lib = _library(name)
    if isinstance(lib, str):
        return lib
    if device_type == "cuda" and not lib[2]:
        return f"the installed spconv is its CPU build (forward only, no CUDA); {INSTALL[name]}"
    if device_type != "cuda" and name == "spconv-triton":
        return f"spconv-triton computes on GPUs only, not on the {device_type}"
    if device_type not in ("cuda", "cpu"):
        return f"{name} computes on CUDA (and spconv's forward on the CPU), not on the {device_type}"
    return None


def choose(device_type: str) -> str:
    """The backend that computes a convolution on ``device_type`` now (an error where the requested one cannot)."""
    want = requested()
    if want == "auto":
        if device_type == "cuda":
            for name in ("spconv", "spconv-triton"):
                if problem(name, device_type) is None:
                    return name
        return "torch"
    why = problem(want, device_type)
    if why:
        source = "using()" if _override else ENV
        raise SparseBackendError(f"sparse backend {want} ({source}) on the {device_type}: {why}")
    return want


def describe(device_type: str) -> str:
    """One line for ``validate``: which backend a convolution on ``device_type`` would use, and why."""
    want = requested()
    try:
        name = choose(device_type)
    except SparseBackendError as exc:
        return f"sparse convolutions: cannot run — {exc}"
    how = f"{ENV}={want}" if not _override else f"using({want!r})"
    return f"sparse convolutions on the {device_type}: {name} ({how})"


def _pairs(book: Any) -> tuple[Tensor, Tensor]:
    """spconv's form of a map, kept on it: (2, K, max pairs) int32 (input rows, output rows; -1 past each offset's
    count) and the counts (K,) int32."""
    if "spconv" in book.cache:
        return book.cache["spconv"]
    device = book.in_idx.device
    bounds = torch.tensor(book.bounds, device=device)
    counts = bounds[1:] - bounds[:-1]
    volume = len(book.bounds) - 1
    width = int(counts.max()) if volume else 0
    pairs = torch.full((2, volume, max(width, 1)), -1, dtype=torch.int32, device=device)
    offset = torch.repeat_interleave(torch.arange(volume, device=device), counts)
    slot = torch.arange(book.in_idx.numel(), device=device) - bounds[:-1][offset]
    pairs[0, offset, slot] = book.in_idx.int()
    pairs[1, offset, slot] = book.out_idx.int()
    book.cache["spconv"] = pairs, counts.int()
    return book.cache["spconv"]


def library_conv(name: str, features: Tensor, weight: Tensor, book: Any, rows_out: int) -> Tensor:
    """The convolution on ``book`` computed by library backend ``name``; ``weight`` (K, in, out) as the torch path
    takes it (passed on as spconv's (out, K, in))."""
    functional, algo, _ = _library(name)  # type: ignore[misc]
    if features.device.type != "cuda" and torch.is_grad_enabled() and (features.requires_grad or
                                                                         weight.requires_grad):
        raise SparseBackendError(f"sparse backend {name} on the {features.device.type}: spconv's CPU build computes "
                                 "the forward only (its backward needs CUDA); compute gradients here with "
                                 f"{ENV}=torch, or run without gradients (torch.no_grad()) for inference")
    pairs, counts = _pairs(book)
    filters = weight.permute(2, 0, 1).contiguous()
    if features.device.type != "cpu":
        return functional.indice_conv(features.contiguous(), filters, pairs, counts, rows_out, algo)
    threads = torch.get_num_threads()  # spconv's CPU forward races with more than one thread: run it with one
    torch.set_num_threads(1)
    try:
        return functional.indice_conv(features.contiguous(), filters, pairs, counts, rows_out, algo)
    finally:
        torch.set_num_threads(threads)


def ran(name: str) -> None:
    """Note that backend ``name`` computed a convolution (for every open :func:`record`)."""
    for seen in _ran:
        seen.add(name)


__all__ = ["CHOICES", "ENV", "SparseBackendError", "choose", "describe", "library_conv", "problem", "ran", "record",
           "requested", "using"]
