"""Which implementation computes a sparse convolution, chosen per call: ``DISTILKIT_SPARSE=auto|torch|spconv|
spconv-triton`` (``auto`` when unset), or :func:`using` in code, which wins over the variable.

* ``torch`` — ``distilkit.sparse.function``: gather, GEMM and scatter-add in PyTorch, forward and backward on
  any device, the same bits in every process.
* ``spconv`` — spconv 2.x's ``indice_conv`` (its gather-GEMM-scatter, ``ConvAlgo.Native``) on distilkit's own
  neighbour maps. Forward and backward on CUDA (a ``spconv-cu1xx`` build); spconv's CPU build (``pip install
  spconv``) computes the forward only — its backward asks for CUDA — so it serves inference on the CPU and a step
  that needs gradients there is refused. spconv 2.3.8's CPU forward races when torch runs more than one thread (its
  own ``SubMConv3d`` gave outputs up to 0.27 apart over five calls on the same input with 2 threads, none apart with
  1; the same on distilkit's maps), so distilkit runs it with one thread.
* ``spconv-triton`` — spconv-Triton's ``indice_conv``, the same functions in Triton (NVIDIA and AMD GPUs; not on
  the CPU).
* ``auto`` — per call, spconv (a CUDA build) where it can take the call, else torch: on CUDA a float32 or float16
  call (or one under float16 autocast) goes to spconv, a float64 or bfloat16 one to torch; elsewhere torch.
  spconv-Triton is used only when named: it compiles and autotunes its Triton kernels for each new problem size, so
  the first steps of a network cost minutes (on an NVIDIA H200 with spconv-triton 1.0.0 and Triton 3.6 under an
  ``auto`` that tried it, the test of one fp32 and one bf16 step of the SCPNet, JS3C-Net and LiDiff paper networks
  ran past its 74 s limit, each).

What each library computes is stated in ``CAPABILITIES`` (device, dtypes, autocast, gradients), read from
spconv 2.3.8's source (the GEMM kernel lists in ``spconv/core.py``: float32 and float16 only; its tuner stops with
"can't find suitable algorithm" for any other dtype, ``csrc/sparse/convops.py``) and spconv-Triton 1.0.0's wheel
(the same dtypes as spconv's, float16 accumulated in float16 for short reductions as spconv does). A call a library cannot take runs on the torch path under
``auto`` (the summary's ``sparse_backend`` then names both); under an explicit ``DISTILKIT_SPARSE=spconv`` it is an
error naming the reason. A neighbour map with no pair never reaches a library (spconv's CUDA code asserts "this
shouldn't happen" on an all-zero map that is not submanifold, forward and backward): its output is zeros (plus the
layer's bias) and its gradients zeros, on the torch path, whatever the backend.

The maps (which input row feeds which output row, per kernel offset) are distilkit's in every backend — only the
products and sums move — so the output rows, their order and the weights' layout (out, k0, k1, k2, in) are the same,
and a checkpoint moves between backends unchanged. spconv 1.x's reuse of a stored map of a smaller kernel K' runs
on every backend as what it is: a convolution of kernel K' whose weight is the first vol(K') slices of this kernel.

An explicitly requested backend that cannot run here is an error naming what is missing; it never falls back.
Under CUDA autocast spconv and spconv-Triton cast their inputs to float16 whatever autocast's dtype
(``custom_fwd(cast_inputs=torch.float16)`` in their ``functional.py``): so they take float16 autocast only, and
bfloat16 autocast runs on the torch path (under ``auto``), which computes in autocast's dtype and sums in float32.
:func:`record` collects which backends ran (a stage's summary names them).

Determinism: spconv's tuner picks a kernel by timing the candidates in each process and its weight-gradient split-k
changes the order of the sums, so two processes can round differently: while PyTorch's deterministic algorithms
are on (``DISTILKIT_DETERMINISTIC``) ``auto`` uses the torch path on CUDA too, whose sums are in a fixed order
(stated in the stage's summary as the backend that ran); an explicit library backend is honoured and the GPU
check's determinism section says whether its bits held.
"""

from __future__ import annotations

import contextlib
import importlib
import os
from dataclasses import dataclass
from functools import cache
from typing import Any, Iterator

import torch
from torch import Tensor

from distilkit.sparse.form import form

from distilkit.sparse.choice import CHOICES, ENV, SparseBackendError, _override, requested

LIBRARIES = {"spconv": "spconv", "spconv-triton": "spconv_triton"}  # backend -> the module it imports
INSTALL = {"spconv": "pip install spconv-cu126 (or spconv-cu121, -cu124: spconv 2.3.8's CUDA builds, one to match "
                     "your CUDA; pip install spconv is the CPU build: forward only)",
           "spconv-triton": "pip install spconv-triton"}


@dataclass(frozen=True)
class Capability:
    """What a library backend computes on one device type: the features' dtypes outside autocast, autocast's dtypes
    it takes part in (the dtype it casts to), whether it has a backward there, and where that was read."""

    dtypes: tuple[torch.dtype, ...]
    autocast: tuple[torch.dtype, ...]
    gradients: bool
    source: str


_HALF_CUDA = Capability((torch.float32, torch.float16), (torch.float16,), True,
                        "spconv/core.py's GEMM kernels: float32 and float16")
# (backend, device type) -> what it computes there; a pair not listed does not run at all. spconv's CPU build
# (cppconstants.CPU_ONLY_BUILD) has no CUDA row and no CPU backward: :func:`capability` says so.
CAPABILITIES: dict[tuple[str, str], Capability] = {
    ("spconv", "cuda"): _HALF_CUDA,
    ("spconv", "cpu"): Capability((torch.float32, torch.float64), (), True,
                                  "spconv's CPU gather-GEMM-scatter: torch.mm on its gathers"),
    ("spconv-triton", "cuda"): Capability((torch.float32, torch.float16), (torch.float16,), True,
                                          "spconv-Triton's Triton kernels: float32 and float16, as spconv's"),
}


@dataclass(frozen=True)
class Call:
    """One convolution as a backend sees it: the device type, the dtype the products run in (autocast's where it is
    on), whether autocast is on, whether a gradient is wanted, and the map's number of pairs."""

    device: str
    dtype: torch.dtype
    autocast: bool = False
    gradients: bool = False
    pairs: int = 1

    @classmethod
    def of(cls, features: Tensor, weight: Tensor, pairs: int) -> "Call":
        device = features.device.type
        auto = torch.is_autocast_enabled(device)
        dtype = torch.get_autocast_dtype(device) if auto else features.dtype
        grads = torch.is_grad_enabled() and (features.requires_grad or weight.requires_grad)
        return cls(device, dtype, auto, grads, pairs)


AUTO_DEVICES = ("cuda",)  # device types where ``auto`` offers a call to the libraries first
AUTO_LIBRARIES = ("spconv",)  # the libraries ``auto`` offers a call to, in order (spconv-triton: only when named)

_ran: list[set[str]] = []  # :func:`record`'s open collections


@contextlib.contextmanager
def using(name: str) -> Iterator[None]:
    """Run the convolutions inside the block on backend ``name`` (one of ``CHOICES``), whatever the variable."""
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


def capability(name: str, device_type: str) -> Capability | None:
    """What library backend ``name`` (installed) computes on ``device_type``; None where it does not run there."""
    cap = CAPABILITIES.get((name, device_type))
    lib = _library(name)
    if cap is None or isinstance(lib, str):
        return cap
    if name == "spconv" and not lib[2]:  # the CPU build: no CUDA, and its backward asks for CUDA
        if device_type == "cuda":
            return None
        return Capability(cap.dtypes, cap.autocast, False, cap.source + " (the CPU build: forward only)")
    return cap


def problem(name: str, device_type: str) -> str | None:
    """Why backend ``name`` cannot compute on ``device_type`` here at all (None: it can take some calls)."""
    if name == "torch":
        return None
    lib = _library(name)
    if isinstance(lib, str):
        return lib
    if capability(name, device_type) is None:
        if name == "spconv" and device_type == "cuda":
            return f"the installed spconv is its CPU build (forward only, no CUDA); {INSTALL[name]}"
        if name == "spconv-triton":
            return f"spconv-triton computes on GPUs only, not on the {device_type}"
        return f"{name} computes on CUDA (and spconv's forward on the CPU), not on the {device_type}"
    return None


def _dtype(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def refusal(name: str, call: Call) -> str | None:
    """Why library backend ``name`` cannot take ``call`` (None: it can)."""
    why = problem(name, call.device)
    if why:
        return why
    cap = capability(name, call.device)
    assert cap is not None
    if call.pairs == 0:
        return "a neighbour map with no pair (spconv's CUDA code asserts on it)"
    if call.autocast and call.dtype not in cap.autocast:
        takes = f"it casts autocast's inputs to {', '.join(map(_dtype, cap.autocast))}" if cap.autocast else \
            "it does not take part in autocast there"
        return f"{_dtype(call.dtype)} autocast on the {call.device}: {takes}"
    if not call.autocast and call.dtype not in cap.dtypes:
        return (f"{_dtype(call.dtype)} features: {name} computes {' and '.join(map(_dtype, cap.dtypes))} only on "
                f"the {call.device} ({cap.source})")
    if call.gradients and not cap.gradients:
        return (f"spconv's CPU build computes the forward only (its backward needs CUDA); compute gradients here "
                f"with {ENV}=torch, or run without gradients (torch.no_grad()) for inference")
    return None


def _deterministic() -> bool:
    return torch.are_deterministic_algorithms_enabled()


def choose(device_type: str, call: Call | None = None) -> str:
    """The backend that computes ``call`` (a float32 call on ``device_type`` when not given) now: under ``auto`` the
    first of ``AUTO_LIBRARIES`` that can take it (on CUDA, and not while PyTorch's deterministic algorithms are
    on), else torch;
    an explicit backend that cannot take it is an error naming the reason."""
    call = call or Call(device_type, torch.float32)
    want = requested()
    if want == "auto":
        if device_type in AUTO_DEVICES and not _deterministic():
            for name in AUTO_LIBRARIES:
                if refusal(name, call) is None:
                    return name
        return "torch"
    if want == "torch":
        return want
    why = refusal(want, call)
    if why:
        source = "using()" if _override else ENV
        raise SparseBackendError(f"sparse backend {want} ({source}) on the {device_type}: {why}"
                                 + ("" if problem(want, device_type) else
                                    f"; {ENV}=auto runs such calls on the torch path"))
    return want


def describe(device_type: str) -> str:
    """One line for ``validate``: which backend a convolution on ``device_type`` would use, and why."""
    want = requested()
    try:
        name = choose(device_type)
    except SparseBackendError as exc:
        return f"sparse convolutions: cannot run — {exc}"
    how = f"{ENV}={want}" if not _override else f"using({want!r})"
    torch_path = f"the torch path's {form(device_type)} form"
    where = "" if name == "torch" or device_type != "cuda" else \
        f" (float64 and bfloat16 calls on {torch_path})"
    if name == "torch":
        name = torch_path
        if want == "auto" and device_type in AUTO_DEVICES and _deterministic():
            kept = [lib for lib in AUTO_LIBRARIES if problem(lib, device_type) is None]
            if kept:
                where = (f" — {', '.join(kept)} is installed but the deterministic settings keep auto off it (its "
                         "tuner times kernels in each process and splits the weight-gradient sums, so two processes "
                         "can round differently); DISTILKIT_DETERMINISTIC=0 or DISTILKIT_SPARSE=spconv uses it")
    return f"sparse convolutions on the {device_type}: {name} ({how}){where}"


def _pairs(book: Any) -> tuple[Tensor, Tensor]:
    """spconv's form of a map, kept on it: (2, K, max pairs) int32 (input rows, output rows; -1 past each offset's
    count) and the counts (K,) int32. Built from the map's host-side bounds: no read back from the device."""
    if "spconv" in book.cache:
        return book.cache["spconv"]
    device = book.in_idx.device
    counts_host = [e - s for s, e in zip(book.bounds[:-1], book.bounds[1:])]
    volume = len(counts_host)
    width = max(counts_host, default=0)
    counts = torch.tensor(counts_host, dtype=torch.int64, device=device)
    starts = torch.tensor(book.bounds[:-1], dtype=torch.int64, device=device)
    pairs = torch.full((2, volume, max(width, 1)), -1, dtype=torch.int32, device=device)
    offset = torch.repeat_interleave(torch.arange(volume, device=device), counts, output_size=book.in_idx.numel())
    slot = torch.arange(book.in_idx.numel(), device=device) - starts[offset]
    pairs[0, offset, slot] = book.in_idx.int()
    pairs[1, offset, slot] = book.out_idx.int()
    book.cache["spconv"] = pairs, counts.int()
    return book.cache["spconv"]


def library_conv(name: str, features: Tensor, weight: Tensor, book: Any, rows_out: int) -> Tensor:
    """The convolution on ``book`` computed by library backend ``name`` (which :func:`choose` found able to take
    it); ``weight`` (K, in, out) as the torch path takes it (passed on as spconv's (out, K, in), contiguous)."""
    functional, algo, _ = _library(name)  # type: ignore[misc]
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


__all__ = ["CAPABILITIES", "CHOICES", "ENV", "Call", "Capability", "SparseBackendError", "capability", "choose",
           "describe", "library_conv", "problem", "ran", "record", "refusal", "requested", "using"]
