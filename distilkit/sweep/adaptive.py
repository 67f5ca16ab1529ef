"""``distilkit sweep FILE --seeds auto``: seeds added in rounds until each method's interval is narrow enough.

The first round runs the sweep file's seeds; each later round adds ``step`` new seeds (the next integers) to every
variant, reusing every finished run, so the methods keep sharing their seeds with the baseline and with each
other. After each round the table's family (:mod:`~distilkit.report.family`: each method at its validation-chosen
weight) gives each method's simultaneous 95 % interval (its corrected one; a lone method's own t-interval); the
sweep stops when every method's is narrower than ``target`` (in the table's units: mIoU points for SSC) or when
``max_seeds`` seeds have run. The rule reads the intervals' widths only, never their position or sign, so it cannot
stop where a difference happens to look good; the report says, for each method, the seed count at which its
interval first became narrower than the target, or its width when the seeds ran out.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError


def widths(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Each method's interval width in the table's units: its simultaneous interval where the table has a family,
    else its own t-interval (nan where it has fewer than two seeds)."""
    out = {}
    for row in rows:
        if not row["delta"] or not row.get("chosen", True) or row.get("control"):  # a control row is no method
            continue
        low, high = row.get("sim_ci", row["delta_ci"])
        out[row["label"]] = row["view"].main[2] * (high - low)
    return out


def next_seeds(seeds: list[int], step: int, max_seeds: int) -> list[int]:
    """``seeds`` with up to ``step`` new ones (the next integers above the largest), ``max_seeds`` at most."""
    out, candidate = list(seeds), max(seeds) + 1
    while len(out) < min(len(seeds) + step, max_seeds):
        out.append(candidate)
        candidate += 1
    return out


def verdicts(history: list[tuple[int, dict[str, float]]], target: float, max_seeds: int) -> list[str]:
    """Per method, why it stopped: the first round's seed count at which its width was under ``target``, else its
    width at the last round (the seeds ran out)."""
    out = []
    for method, last in history[-1][1].items():
        clear = next((n for n, w in history if not math.isnan(w.get(method, math.nan)) and w[method] < target), None)
        if clear is not None:
            out.append(f"{method}: interval narrower than {target:g} at {clear} seeds "
                       f"({history[-1][1][method]:.2f} wide at {history[-1][0]})")
        else:
            out.append(f"{method}: {last:.2f} wide at {history[-1][0]} seeds — the limit of {max_seeds} seeds "
                       f"stopped it, not the target {target:g}")
    return out


def run_until_clear(path: str | Path, output: str | Path, jobs: int, target: float, max_seeds: int, step: int = 2,
                    quiet: bool = False) -> Path | None:
    """Run the sweep in rounds (see the module) and write its table with a note on the stopping rule."""
    from distilkit.sweep.results import sweep_rows
    from distilkit.sweep.runner import SweepRun
    from distilkit.sweep.spec import load_sweep

    if not target > 0 or max_seeds < 2 or step < 1:
        raise DistilkitError(f"--seeds auto: --target-width must be > 0, --max-seeds at least 2 and --seed-step at "
                             f"least 1 (got {target:g}, {max_seeds}, {step})")
    spec = load_sweep(path)  # read once: every round's SweepRun shares it
    seeds = list(spec.spec.seeds)[:max_seeds]
    if len(seeds) < 2:
        seeds = next_seeds(seeds, 2 - len(seeds), max_seeds)
    history: list[tuple[int, dict[str, float]]] = []
    failures: list[str] = []
    while True:
        sweep = SweepRun(spec, output, seeds, quiet=quiet)
        failures += sweep.run(jobs)
        records, _ = sweep.records()
        rows, _ = sweep_rows(records, sweep.sweep.baseline, sweep.order())
        history.append((len(seeds), widths(rows)))
        wide = [m for m, w in history[-1][1].items() if math.isnan(w) or not w < target]
        if not quiet:
            sweep.console.print(f"--seeds auto: {len(seeds)} seeds, "
                                + (f"{len(wide)} method(s) wider than {target:g}: {', '.join(wide)}" if wide else
                                   f"every method's interval narrower than {target:g}"), highlight=False)
        if not wide or len(seeds) >= max_seeds:
            break
        seeds = next_seeds(seeds, step, max_seeds)
    lines = verdicts(history, target, max_seeds)
    note = (f"Seeds chosen by `--seeds auto` ({', '.join(map(str, seeds))}): rounds of {step} seeds added to every "
            f"variant until each method's simultaneous 95 % interval was narrower than {target:g} or {max_seeds} "
            "seeds had run; the rule read the widths only, never the differences' sign or size. " + "; ".join(lines)
            + ".")
    result = sweep.collect(notes=[note])
    if failures:
        raise DistilkitError("some runs failed (the others are in the table):\n  " + "\n  ".join(failures))
    return result


__all__ = ["next_seeds", "run_until_clear", "verdicts", "widths"]
