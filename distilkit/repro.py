"""Bitwise-repeatable runs: the same recipe and seed give the same checkpoints in any process on one machine.

Two things vary between processes on the CPU unless they are pinned:

* PyTorch's CPU backward of advanced indexing (``x[idx]`` with repeated indices, e.g. gathering k nearest
  neighbours) accumulates from several threads in a racy order; ``torch.use_deterministic_algorithms`` makes it
  (and every other op that has a deterministic variant) deterministic — on while a stage runs;
* MKL's vector maths (VML: PyTorch's ``exp``, ``log``, ``tanh``, ``erf``, ... on contiguous float tensors) picks
  its implementation for the processor at a function's first call; when two threads make that first call at once
  (a tensor large enough for PyTorch to split it), one of them may compute its half with another implementation,
  1 ulp apart — so the first ``exp`` of a process differs from its later ones in about a third of processes
  under load (found with the two-process and killed-EMA-run tests, 2026-11-27). :func:`warm_vector_math` makes every
  such first call once in one thread, before a stage runs;
* MKL's reductions may depend on the memory alignment of an operand (a view into a tensor); its strict
  conditional numerical reproducibility (``MKL_CBWR=AUTO,STRICT``) pins them, and cuBLAS needs a fixed workspace
  (``CUBLAS_WORKSPACE_CONFIG``) — both read when the libraries first run, so ``import distilkit`` sets them (the
  command line imports it before torch; subprocesses, sweeps' jobs and torchrun's children inherit them). A program
  that multiplies matrices with torch before it imports distilkit keeps MKL's default mode.

On CUDA the same context also turns cuDNN's deterministic mode on and its benchmarking off; an op that has no
deterministic variant only warns (``warn_only``), and :func:`nondeterministic_ops` collects those warnings so that a
stage's summary names the ops that made it not repeatable.

On by default; ``DISTILKIT_DETERMINISTIC=0`` turns both off (faster where the deterministic variants are slower).
Same numbers need the same thread count and the same processor too (``torch.get_num_threads()`` and
:func:`processor`, recorded in each stage's summary): MKL and oneDNN choose their kernels by the CPU's instruction
sets.
"""

from __future__ import annotations

import contextlib
import os
import warnings
from typing import Any, Iterator

ENV = "DISTILKIT_DETERMINISTIC"
LIBRARY_ENV = {"MKL_CBWR": "AUTO,STRICT", "CUBLAS_WORKSPACE_CONFIG": ":4096:8"}


def enabled() -> bool:
    """Whether runs are made bitwise repeatable (``DISTILKIT_DETERMINISTIC``, default on)."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def set_environment() -> None:
    """Before torch loads: the libraries' reproducibility settings, unless the user set them (or opted out)."""
    if enabled():
        for key, value in LIBRARY_ENV.items():
            os.environ.setdefault(key, value)


def set_deterministic(on: bool, warn_only: bool = False) -> None:
    """``torch.use_deterministic_algorithms`` without its import of ``torch._inductor`` (1.1 s of CPU in each new
    process, torch 2.13) where inductor is not loaded: the setting it adds there (``inductor.config.deterministic``)
    only concerns ``torch.compile``, which distilkit does not use; where inductor is loaded, the public call."""
    import sys

    import torch

    private = getattr(torch._C, "_set_deterministic_algorithms", None)
    if private is None or "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(on, warn_only=warn_only)
    else:
        private(on, warn_only=warn_only)


# PyTorch's unary ops that call MKL's VML on contiguous float32/float64 tensors (ATen/cpu/vml.h), and their neighbours
VECTOR_MATH = ("abs", "acos", "asin", "atan", "cos", "cosh", "erf", "erfc", "erfinv", "exp", "expm1", "log", "log10",
               "log1p", "log2", "lgamma", "rsqrt", "sigmoid", "sin", "sinh", "sqrt", "tan", "tanh", "trunc")
_WARMED: list[bool] = []


def warm_vector_math() -> bool:
    """Each of :data:`VECTOR_MATH` called once, in this thread, on 64 values of float32 and of float64 (below
    PyTorch's grain size: never split between threads), so that MKL's per-function dispatch is settled before any
    two threads can race to it; once per process (a forked child inherits it). True where it ran now."""
    import torch

    if _WARMED:
        return False
    for dtype in (torch.float32, torch.float64):
        x = torch.linspace(-0.9, 0.9, 64, dtype=dtype)
        for name in VECTOR_MATH:
            getattr(torch, name)(x.abs() + 0.05 if name in ("log", "log10", "log2", "lgamma", "rsqrt", "sqrt") else x)
    _WARMED.append(True)
    return True


def vector_math_warmed() -> bool:
    """Whether :func:`warm_vector_math` ran in this process (a stage's summary records it)."""
    return bool(_WARMED)


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[bool]:
    """PyTorch's deterministic variants of its ops while a stage runs (a warning, not an error, for an op that has
    none), the process's previous setting restored after; yields whether they are on."""
    import torch

    on = enabled()
    was = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
           torch.utils.deterministic.fill_uninitialized_memory)  # type: ignore[attr-defined]
    cudnn = torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark
    mkldnn = torch.backends.mkldnn.deterministic
    set_deterministic(on, warn_only=True)
    if on:
        warm_vector_math()
    # oneDNN (CPU convolutions) may use atomics in some implementations unless told not to (its "deterministic"
    # attribute; PyTorch passes it where its oneDNN calls take it)
    torch.backends.mkldnn.deterministic = on or mkldnn
    # a debugging aid that fills every new tensor with NaN in deterministic mode: no result depends on it, and it
    # cost 15 % of an SCPNet step here
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]
    if on:  # cuDNN: its deterministic convolutions, and no benchmarking (which picks algorithms by timing)
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        yield on
    finally:
        set_deterministic(was[0], warn_only=was[1])
        torch.utils.deterministic.fill_uninitialized_memory = was[2]  # type: ignore[attr-defined]
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = cudnn
        torch.backends.mkldnn.deterministic = mkldnn


def processor() -> str:
    """The CPU's model name (Linux: ``/proc/cpuinfo``) and the instruction set PyTorch's kernels dispatch to, e.g.
    "Intel(R) Xeon(R) Processor (AVX512)"."""
    import platform

    import torch

    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            name = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), name)
    except OSError:
        pass
    return f"{name} ({torch.backends.cpu.get_cpu_capability()})"


# MKL's code branches as mkl_cbwr_get reports them (mkl_service.h); 1 is "not set", MKL's default
MKL_BRANCHES = {0: "OFF", 1: "off", 2: "AUTO", 3: "COMPATIBLE", 4: "SSE2", 6: "SSSE3", 7: "SSE4_1", 8: "SSE4_2",
                9: "AVX", 10: "AVX2", 11: "AVX512_MIC", 12: "AVX512", 13: "AVX512_MIC_E1", 14: "AVX512_E1"}
MKL_STRICT = 0x10000


def mkl_cbwr() -> str | None:
    """MKL's conditional numerical reproducibility as MKL itself reports it in this process, e.g.
    ``"AUTO,STRICT (AVX512_E1)"`` (the branch AUTO chose in brackets) or ``"off"`` — read back through the MKL service
    functions that PyTorch's x86 builds export, so a summary says what MKL ran with, not what the environment asked
    for (MKL reads ``MKL_CBWR`` once, at its first call). None where PyTorch has no MKL (ARM, macOS)."""
    import ctypes

    import torch

    if not torch.backends.mkl.is_available():
        return None
    try:
        lib = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
        get, auto = lib.mkl_serv_cbwr_get, lib.mkl_serv_cbwr_get_auto_branch
    except (OSError, AttributeError):
        return None
    get.argtypes, get.restype, auto.restype = [ctypes.c_int], ctypes.c_int, ctypes.c_int
    mode = get(-1)  # MKL_CBWR_ALL
    text = MKL_BRANCHES.get(mode & 0xFFFF, str(mode & 0xFFFF)) + (",STRICT" if mode & MKL_STRICT else "")
    return f"{text} ({MKL_BRANCHES.get(auto(), '?')})" if mode & 0xFFFF == 2 else text


NOT_DETERMINISTIC = "does not have a deterministic implementation"


@contextlib.contextmanager
def nondeterministic_ops() -> Iterator[list[str]]:
    """The ops that ran without a deterministic variant while the context was open, in the order first seen: PyTorch
    warns of each (``warn_only``) and the run goes on, not bitwise repeatable; their warnings are collected here (a
    stage's summary names them) instead of printed, every other warning shown as before."""
    seen: list[str] = []
    with warnings.catch_warnings():  # restores the filters and warnings.showwarning on the way out
        warnings.filterwarnings("always", message=f".*{NOT_DETERMINISTIC}")
        shown = warnings.showwarning

        def show(message: Any, category: Any, filename: str, lineno: int, file: Any = None, line: Any = None) -> None:
            text = str(message)
            if NOT_DETERMINISTIC not in text:
                shown(message, category, filename, lineno, file, line)
                return
            op = text.split(NOT_DETERMINISTIC)[0].strip()
            if op not in seen:
                seen.append(op)

        warnings.showwarning = show
        yield seen
