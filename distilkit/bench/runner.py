"""``distilkit bench [NAME ...]``: runs the registered benchmarks (:data:`distilkit.bench.base.BENCHES`) and prints
one table — fast and naive milliseconds, peak memory, speed-up and the relative error between the two forms, and the
columns of their own that cases add (``distilkit bench step``'s reserved memory, host syncs, ...) — with the notes
under it: each case's line, and why each case that did not run did not."""

from __future__ import annotations

import fnmatch
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from distilkit.bench.base import BENCHES, DEADLINE, SCRATCH, Case, Skipped, time_fb

COMPARED = ("naive ms", "naive peak", "speed-up", "rel. error (vs naive, or float64)")  # left out where no row has one


def _fmt_mem(b: int | None) -> str:
    return "n/a" if b is None else f"{max(b, 0) / 2**20:,.0f} MiB"


def pattern_of(case: Case, only: list[str] | None) -> int | None:
    """The index of the first of ``only`` that ``case`` matches (patterns matched against its objective and size:
    ``SCPNet`` anywhere, ``SCPNet*bf16`` both in that order; case-insensitive), None where none does; 0 for every
    case without ``only``."""
    if not only:
        return 0
    label = f"{case.objective} {case.size}".lower()
    return next((i for i, pattern in enumerate(only) if fnmatch.fnmatchcase(label, f"*{pattern.lower()}*")), None)


def selected(cases: list[Case], only: list[str] | None) -> list[Case]:
    """The cases that match one of ``only``, those of its first pattern first, then the second's, ... (each
    pattern's in the benchmark's order); every case without ``only``."""
    marked = [(pattern_of(case, only), i, case) for i, case in enumerate(cases)]
    return [case for _, _, case in sorted((m for m in marked if m[0] is not None), key=lambda m: (m[0], m[1]))]


def run_bench(names: list[str], device: str = "cpu", quick: bool = False, repeat: int | None = None,
              only: list[str] | None = None, time_limit: float | None = None) -> list[dict]:
    """Each benchmark of ``names`` (every one: empty) timed and printed as one table; its rows. ``only``: just the
    cases that match one of these patterns, in the patterns' order (:func:`selected`); ``time_limit``: seconds from
    the start after which no case starts (and a case that checks :func:`~distilkit.bench.base.time_left` stops), each
    one left said so under the table. What the benchmarks write (exported scans, their runs' data: ``scratch_dir``)
    goes to one temporary folder, removed at the end."""
    with tempfile.TemporaryDirectory(prefix="distilkit-bench-", ignore_cleanup_errors=True) as root:
        SCRATCH.append(Path(root))
        DEADLINE.append(time.monotonic() + time_limit if time_limit is not None else float("inf"))
        try:
            return _run_bench(names, device, quick, repeat, only, time_limit)
        finally:
            SCRATCH.pop()
            DEADLINE.pop()


def _run_bench(names: list[str], device: str, quick: bool, repeat: int | None, only: list[str] | None,
               time_limit: float | None) -> list[dict]:
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
    rows: list[dict] = []
    cells: list[dict[str, str]] = []
    notes: list[str] = []
    late: list[str] = []  # cases the time limit left
    matched = 0
    reps = repeat or (3 if not quick else 2)
    for name in names or list(BENCHES):
        built = BENCHES[name](dev, quick)
        chosen = selected([case for case in built if case.skipped is None], only)
        if only and not chosen:
            continue
        matched += len(chosen)
        # what cannot run here is said whenever the benchmark runs (it explains a row the selection misses)
        notes += [f"{case.objective} ({case.size}): skipped — {case.skipped}" for case in built if case.skipped]
        for case in chosen:
            what = f"{case.objective} ({case.size})"
            if time_limit is not None and DEADLINE[-1] <= time.monotonic():
                late.append(what)
                continue
            with console.status(f"{case.objective} {case.size}"):
                try:
                    row = _measure(case, dev, reps)
                except Skipped as exc:
                    notes.append(f"{what}: skipped — {exc}")
                    continue
            rows.append(row)
            if case.note is not None:
                notes.append(case.note(row))
            cells.append({"objective": case.objective, "size": case.size, "fast ms": f"{row['fast_ms']:,.1f}",
                          "fast peak": _fmt_mem(row["fast_peak"]),
                          "naive ms": f"{row['naive_ms']:,.1f}" if "naive_ms" in row else "—",
                          "naive peak": _fmt_mem(row.get("naive_peak")) if "naive_ms" in row else "—",
                          "speed-up": (f"{row['speedup']:,.0f}×" if row["speedup"] >= 10 else
                                       f"{row['speedup']:.2f}×") if "speedup" in row else "—",
                          COMPARED[-1]: f"{row['rel_err']:.1e}" if "rel_err" in row else "—",
                          **case.columns})
    if only and not matched:
        raise DistilkitError(f"--only {' '.join(only)}: no case of {', '.join(names or BENCHES)} matches")
    if late:
        notes.append(f"skipped — the time limit of {time_limit:.0f} s was reached before they started: "
                     + "; ".join(late))
    table = Table(title=f"distilkit bench — {dev.type}, torch {torch.__version__}, {torch.get_num_threads()} threads "
                        "(ms: forward + backward unless the benchmark's rows time something else, as their notes say)")
    if dev.type == "cpu" and any(c["fast peak"] not in ("n/a", "—") for c in cells):
        notes.append("peak (CPU): the process's resident high-water mark above what it held before the row "
                     "(/proc/self/status VmHWM after clear_refs): a lower bound — memory the allocator already held "
                     "and reuses does not count; on CUDA it is the allocator's exact peak")
    columns = ["objective", "size", "fast ms", "fast peak"]
    if not cells or any(c[col] != "—" for c in cells for col in COMPARED):  # some row compares two forms
        columns += COMPARED
    columns += dict.fromkeys(col for c in cells for col in c if col not in columns and col not in COMPARED)
    for col in columns:
        table.add_column(col, justify="left" if col in ("objective", "size") else "right")
    for c in cells:
        table.add_row(*(c.get(col, "—") for col in columns))
    console.print(table)
    for line in notes:
        console.print(line, highlight=False, soft_wrap=True)
    return rows


def _measure(case: Case, dev: torch.device, reps: int) -> dict[str, Any]:
    """A case's row: its own measurement or forward+backward timed, against its naive form or float64 value."""
    ms, peak, val = case.measure() if case.measure else time_fb(case.fast, case.inputs, dev, reps)
    row: dict[str, Any] = {"objective": case.objective, "size": case.size, "fast_ms": ms, "fast_peak": peak,
                           "value": val, **({"columns": dict(case.columns)} if case.columns else {})}
    if case.reference is not None:
        with torch.no_grad():
            ref = float(case.reference())
        row.update(rel_err=abs(val - ref) / max(abs(ref), 1e-30))
    if case.naive is not None:
        nms, npeak, nval = time_fb(case.naive, case.inputs, dev, reps)
        row.update(naive_ms=nms, naive_peak=npeak, speedup=nms / ms)
        if case.same_value:
            row.update(rel_err=abs(val - nval) / max(abs(nval), 1e-30))
    return row
