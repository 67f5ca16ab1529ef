"""``distilkit bench [NAME ...]``: runs the registered benchmarks (:data:`distilkit.bench.base.BENCHES`) and prints
one table — fast and naive milliseconds, peak memory, speed-up and the relative error between the two forms."""

from __future__ import annotations

import tempfile
from pathlib import Path

import torch

from distilkit.bench.base import BENCHES, SCRATCH, time_fb


def _fmt_mem(b: int | None) -> str:
    return "n/a" if b is None else f"{max(b, 0) / 2**20:,.0f} MiB"


def run_bench(names: list[str], device: str = "cpu", quick: bool = False, repeat: int | None = None) -> list[dict]:
    """Each benchmark of ``names`` (every one: empty) timed and printed as one table; its rows. What the benchmarks
    write (exported scans, their runs' data: ``scratch_dir``) goes to one temporary folder, removed at the end."""
    with tempfile.TemporaryDirectory(prefix="distilkit-bench-", ignore_cleanup_errors=True) as root:
        SCRATCH.append(Path(root))
        try:
            return _run_bench(names, device, quick, repeat)
        finally:
            SCRATCH.pop()


def _run_bench(names: list[str], device: str, quick: bool, repeat: int | None) -> list[dict]:
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
    for col in ("objective", "size", "fast ms", "fast peak", "naive ms", "naive peak", "speed-up",
                "rel. error (vs naive, or float64)"):
        table.add_column(col, justify="left" if col in ("objective", "size") else "right")
    rows = []
    notes: list[str] = []
    reps = repeat or (3 if not quick else 2)
    for name in names or list(BENCHES):
        for case in BENCHES[name](dev, quick):
            with console.status(f"{case.objective} {case.size}"):
                ms, peak, val = case.measure() if case.measure else time_fb(case.fast, case.inputs, dev, reps)
                row = {"objective": case.objective, "size": case.size, "fast_ms": ms, "fast_peak": peak, "value": val}
                if case.reference is not None:
                    with torch.no_grad():
                        ref = float(case.reference())
                    row.update(rel_err=abs(val - ref) / max(abs(ref), 1e-30))
                if case.naive is not None:
                    nms, npeak, nval = time_fb(case.naive, case.inputs, dev, reps)
                    row.update(naive_ms=nms, naive_peak=npeak, speedup=nms / ms)
                    if case.same_value:
                        row.update(rel_err=abs(val - nval) / max(abs(nval), 1e-30))
            rows.append(row)
            if case.note is not None:
                notes.append(case.note(row))
            table.add_row(case.objective, case.size, f"{ms:,.1f}", _fmt_mem(peak),
                          f"{row['naive_ms']:,.1f}" if "naive_ms" in row else "—",
                          _fmt_mem(row.get("naive_peak")) if "naive_ms" in row else "—",
                          (f"{row['speedup']:,.0f}×" if row["speedup"] >= 10 else f"{row['speedup']:.2f}×") if "speedup" in row else "—",
                          f"{row['rel_err']:.1e}" if "rel_err" in row else "—")
    console.print(table)
    for line in notes:
        console.print(line, highlight=False, soft_wrap=True)
    return rows

