"""``distilkit bench``: forward+backward timings of objectives at realistic 3-D sizes.

Each case times the fast (shipped) form and, where it fits in memory, the naive form of the
paper's formula on the same inputs, side by side in one run. Peak memory is the growth of the
process's peak resident set (Linux ``VmHWM``, reset through ``/proc/self/clear_refs``) on the
CPU, or ``torch.cuda.max_memory_allocated`` on CUDA.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch
from torch import Tensor


@dataclass
class Case:
    objective: str
    size: str
    fast: Callable[[], Tensor]
    naive: Callable[[], Tensor] | None
    inputs: list[Tensor]


def _peak_reset(device: torch.device) -> None:
    gc.collect()
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        return
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _peak_bytes(device: torch.device, base: int) -> int | None:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) - base
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 - base
    except OSError:
        return None
    return None


def _rss(device: torch.device) -> int:
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
        out.backward()
        return float(out.detach())

    value = once()  # warm-up
    times = []
    _peak_reset(device)
    base = _rss(device)
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        value = once()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append((time.perf_counter() - t0) * 1000)
    peak = _peak_bytes(device, base)
    times.sort()
    return times[len(times) // 2], peak, value


def naive_dskd(fs: Tensor, ft: Tensor) -> Tensor:
    """SCPNet eq. 1-2 literally, with the two N x N cosine matrices."""
    a = torch.nn.functional.normalize(fs, dim=1)
    b = torch.nn.functional.normalize(ft, dim=1)
    return ((a @ a.T - b @ b.T) ** 2).mean()


def dskd_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import dskd

    cases = []
    big = 20_000 if quick else 1_000_000
    small = 2_000 if quick else 16_000
    for n, with_naive in ((big, False), (small, True)):
        g = torch.Generator(device="cpu").manual_seed(0)
        fs = torch.randn(n, 32, generator=g).to(device).requires_grad_(True)
        ft = torch.randn(n, 32, generator=g).to(device)
        cases.append(Case("dskd", f"{n:,} × 32", lambda fs=fs, ft=ft: dskd(fs, ft),
                          (lambda fs=fs, ft=ft: naive_dskd(fs, ft)) if with_naive else None, [fs]))
    return cases


BENCHES: dict[str, Callable[[torch.device, bool], list[Case]]] = {"dskd": dskd_cases}


def _fmt_mem(b: int | None) -> str:
    return "n/a" if b is None else f"{max(b, 0) / 2**20:,.0f} MiB"


def run_bench(names: list[str], device: str = "cpu", quick: bool = False, repeat: int | None = None) -> list[dict]:
    from rich.table import Table

    from distilkit.console import make_console

    from distilkit.errors import DistilkitError

    unknown = [n for n in names if n not in BENCHES]
    if unknown:
        import difflib

        hints = [difflib.get_close_matches(n, list(BENCHES), n=1) for n in unknown]
        raise DistilkitError(f"no benchmark for {', '.join(map(repr, unknown))}"
                             + "".join(f"; did you mean {h[0]!r}?" for h in hints if h)
                             + f" (available: {', '.join(BENCHES)})")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise DistilkitError("--device cuda: CUDA is not available on this machine")
    console = make_console()
    table = Table(title=f"distilkit bench — forward+backward, {dev.type}, torch {torch.__version__}, "
                        f"{torch.get_num_threads()} threads")
    for col in ("objective", "size", "fast ms", "fast peak", "naive ms", "naive peak", "speed-up", "|fast-naive|/naive"):
        table.add_column(col, justify="left" if col in ("objective", "size") else "right")
    rows = []
    reps = repeat or (3 if not quick else 2)
    for name in names or list(BENCHES):
        for case in BENCHES[name](dev, quick):
            with console.status(f"{case.objective} {case.size}"):
                ms, peak, val = time_fb(case.fast, case.inputs, dev, reps)
                row = {"objective": case.objective, "size": case.size, "fast_ms": ms, "fast_peak": peak, "value": val}
                if case.naive is not None:
                    nms, npeak, nval = time_fb(case.naive, case.inputs, dev, reps)
                    row.update(naive_ms=nms, naive_peak=npeak, speedup=nms / ms,
                               rel_err=abs(val - nval) / max(abs(nval), 1e-30))
            rows.append(row)
            table.add_row(case.objective, case.size, f"{ms:,.1f}", _fmt_mem(peak),
                          f"{row['naive_ms']:,.1f}" if "naive_ms" in row else "—",
                          _fmt_mem(row.get("naive_peak")) if "naive_ms" in row else "—",
                          f"{row['speedup']:,.0f}×" if "speedup" in row else "—",
                          f"{row['rel_err']:.1e}" if "rel_err" in row else "—")
    console.print(table)
    return rows
