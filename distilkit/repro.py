"""Bitwise-repeatable runs: the same recipe and seed give the same checkpoints in any process on one machine.

Two things vary between processes on the CPU unless they are pinned:

* PyTorch's CPU backward of advanced indexing (``x[idx]`` with repeated indices, e.g. gathering k nearest
  neighbours) accumulates from several threads in a racy order; ``torch.use_deterministic_algorithms`` makes it
  (and every other op that has a deterministic variant) deterministic — on while a stage runs;
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


@contextlib.contextmanager
def deterministic_algorithms() -> Iterator[bool]:
    """PyTorch's deterministic variants of its ops while a stage runs (a warning, not an error, for an op that has
    none), the process's previous setting restored after; yields whether they are on."""
    import torch

    on = enabled()
    was = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled(),
           torch.utils.deterministic.fill_uninitialized_memory)  # type: ignore[attr-defined]
    cudnn = torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark
    torch.use_deterministic_algorithms(on, warn_only=True)
    # a debugging aid that fills every new tensor with NaN in deterministic mode: no result depends on it, and it
    # cost 15 % of an SCPNet step here
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]
    if on:  # cuDNN: its deterministic convolutions, and no benchmarking (which picks algorithms by timing)
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = True, False
    try:
        yield on
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])
        torch.utils.deterministic.fill_uninitialized_memory = was[2]  # type: ignore[attr-defined]
        torch.backends.cudnn.deterministic, torch.backends.cudnn.benchmark = cudnn


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
