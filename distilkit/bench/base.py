"""What every ``distilkit bench`` benchmark shares, and nothing else: a :class:`Case` (the fast, shipped form timed
against the naive form of the paper's formula on the same inputs, side by side in one run), forward+backward timing
with peak memory (:func:`time_fb`), and the registry of benchmarks by name (:data:`BENCHES`, filled by
:func:`register`) that :mod:`distilkit.bench.runner` reads. A case may measure itself (``measure``), add columns of
its own to its row (``columns``), or say why it cannot run here (``skipped``, or :class:`Skipped` from ``measure``;
a line under the table, never a silent gap); :func:`time_left` is the running bench's time limit. A benchmark module
registers its cases here and imports no other benchmark (an import-linter contract in ``pyproject.toml``).

Peak memory is the growth of the process's peak resident set (Linux ``VmHWM``, reset through
``/proc/self/clear_refs``) on the CPU, or ``torch.cuda.max_memory_allocated`` on CUDA.
"""

from __future__ import annotations

import gc
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor


SCRATCH: list[Path] = []  # the temporary folder of the running ``run_bench`` (removed when it ends)


def scratch_dir(prefix: str) -> Path:
    """A new folder for a benchmark's files (an exported scan, a run's data): inside the running ``run_bench``'s
    temporary folder, which is removed when it ends; outside one, a new temporary folder of the caller's."""
    return Path(tempfile.mkdtemp(prefix=prefix, dir=SCRATCH[-1] if SCRATCH else None))


@dataclass
class Case:
    objective: str
    size: str
    fast: Callable[[], Tensor]
    naive: Callable[[], Tensor] | None
    inputs: list[Tensor]
    reference: Callable[[], Tensor] | None = None  # float64 value where the naive form does not fit
    same_value: bool = True  # False: the two forms compute different things (a sampler at other step counts)
    note: Callable[[dict[str, Any]], str] | None = None  # a line under the table from the timed row (e.g. GFLOP/s)
    measure: Callable[[], tuple[float, int | None, float]] | None = None  # its own (ms, peak bytes, value)
    columns: dict[str, str] = field(default_factory=dict)  # more figures of its row (column -> text), set by measure
    skipped: str | None = None  # why it cannot run here: a line under the table instead of a row


class Skipped(Exception):
    """Raised by a case's ``measure`` that cannot run here after all (a backend that refuses the call, the device's
    memory, the time limit): the runner prints the reason under the table instead of a row."""


DEADLINE: list[float] = []  # the running ``run_bench``'s time limit (``time.monotonic()``), if it has one


def time_left() -> float:
    """Seconds until the running ``run_bench``'s time limit (infinite without one): a case that times many steps
    checks it between them and raises :class:`Skipped` when it is past."""
    return DEADLINE[-1] - time.monotonic() if DEADLINE else float("inf")


def peak_reset(device: torch.device) -> None:
    """Start a peak measurement: the allocator's peak on CUDA, the process's high-water mark on the CPU."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def peak_bytes(device: torch.device, base: int) -> int | None:
    """The peak since :func:`peak_reset`, less ``base`` (None where the system does not say)."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) - base
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 - base
    except OSError:
        return None
    return None


def resident_bytes(device: torch.device) -> int:
    """What is held now: torch's allocations on CUDA, the process's resident size on the CPU."""
    if device.type == "cuda":
        return torch.cuda.memory_allocated(device)
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 0


def time_fb(fn: Callable[[], Tensor], inputs: list[Tensor], device: torch.device, repeat: int) -> tuple[float, int | None, float]:
    """Median milliseconds of forward+backward, peak extra memory in bytes, and the value."""
    def once() -> float:
        for t in inputs:
            t.grad = None
        out = fn()
        if out.requires_grad:  # a case without trainable input (key-point selection) times its forward
            out.backward()
        return float(out.detach())

    value = once()  # warm-up
    times = []
    peak_reset(device)
    base = resident_bytes(device)
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        value = once()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append((time.perf_counter() - t0) * 1000)
    peak = peak_bytes(device, base)
    times.sort()
    return times[len(times) // 2], peak, value



CaseFn = Callable[[torch.device, bool], list[Case]]

# name -> the function that builds a benchmark's cases for a device (quick: small sizes); in the order registered
BENCHES: dict[str, CaseFn] = {}


def register(name: str) -> Callable[[CaseFn], CaseFn]:
    """Register a benchmark's cases under ``name`` (``distilkit bench NAME``)."""
    def add(fn: CaseFn) -> CaseFn:
        if name in BENCHES:
            raise ValueError(f"benchmark {name!r} is registered twice")
        BENCHES[name] = fn
        return fn
    return add
