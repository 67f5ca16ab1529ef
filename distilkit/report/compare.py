"""Two stage runs side by side (``distilkit compare RUN_A RUN_B``): what differs in their configuration, their
scores at both checkpoints with the difference B − A, per-class scores, loss curves on shared axes and their
bird's-eye previews. Written as ``compare.md`` + ``compare.png`` and printed as a table."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from distilkit.files import atomic_write_text
from distilkit.report.scores import ScoreView, stage_row
from distilkit.errors import DistilkitError
from distilkit.report import plots
from distilkit.report.run import class_table, read_run

SKIP = {"distilkit", "hash"}


def _flat(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d} if d is not None else {}  # None and absent read the same


def config_diff(a: Path, b: Path) -> list[tuple[str, Any, Any]]:
    """(dotted key, A's value, B's value) for each resolved-configuration entry that differs."""
    def load(p: Path) -> dict[str, Any]:
        f = p / "recipe.resolved.yaml"
        return _flat({k: v for k, v in (yaml.safe_load(f.read_text(encoding="utf-8")) or {}).items()
                      if k not in SKIP}) if f.is_file() else {}

    fa, fb = load(a), load(b)
    return [(k, fa.get(k, "—"), fb.get(k, "—")) for k in sorted(set(fa) | set(fb)) if fa.get(k, "—") != fb.get(k, "—")]


def _fmt_delta(col: tuple[str, str, float], d: float) -> str:
    if d != d:  # NaN: a score one of the runs lacks
        return "—"
    return f"{col[2] * d:+.2f}" if col[2] != 1.0 else f"{d:+.4g}"


def class_scores(summary: dict[str, Any], row: dict[str, Any], view: ScoreView) -> dict[str, float]:
    """A run's per-class scores at its best checkpoint by class name (its own class table)."""
    names, _ = class_table(summary, view)
    return dict(zip(names, row["class_scores"]))


def class_rows(sa: dict[str, Any], ra: dict[str, Any], sb: dict[str, Any], rb: dict[str, Any],
               view: ScoreView) -> tuple[list[tuple[str, float, float]], str | None]:
    """(class, A's score, B's score) matched by class name — A's classes in A's order, then B's own (NaN where a
    run has no such class) — and a line naming the classes either run lacks (None when both have the same)."""
    a, b = class_scores(sa, ra, view), class_scores(sb, rb, view)
    nan = float("nan")
    rows = [(n, a.get(n, nan), b.get(n, nan)) for n in [*a, *(n for n in b if n not in a)]]
    b_lacks, a_lacks = [n for n in a if n not in b], [n for n in b if n not in a]
    if not b_lacks and not a_lacks:
        return rows, None
    parts = [f"B lacks {len(b_lacks)} of A's classes: {', '.join(b_lacks)}" if b_lacks else "",
             f"A lacks {len(a_lacks)} of B's: {', '.join(a_lacks)}" if a_lacks else ""]
    return rows, ("the two runs have different class tables (rows matched by class name; each mIoU averages its "
                  f"own run's classes): {'; '.join(p for p in parts if p)}")


def _class_cells(scale: float, va: float, vb: float) -> list[str]:
    """A per-class row's A, B and B − A cells ("—" where a run has no such class)."""
    def one(v: float, sign: str = "") -> str:
        return "—" if v != v else f"{scale * v:{sign}.1f}"

    return [one(va), one(vb), one(vb - va, "+")]


def compare_rows(ra: dict[str, Any], rb: dict[str, Any]) -> list[list[str]]:
    view: ScoreView = ra["view"]
    rows = []
    for which in ("best", "last"):
        for col in view.columns:
            a, b = ra[which][col[0]], rb[which][col[0]]
            rows.append([f"{col[1]} {which}", view.fmt(col, a), view.fmt(col, b), _fmt_delta(col, b - a)])
    return rows


def compare_runs(run_a: str | Path, run_b: str | Path, out: str | Path | None = None, console: Any = None) -> Path:
    """Print the comparison and write ``compare.md`` and ``compare.png`` to ``out`` (default: a folder
    ``compare-<A>-vs-<B>`` beside run A)."""
    a, sa = read_run(run_a)
    b, sb = read_run(run_b)
    ra, rb = stage_row(sa), stage_row(sb)
    if ra["view"] != rb["view"]:
        raise DistilkitError(f"{a.name} is scored by {ra['view'].metric} ({ra['view'].select}), {b.name} by "
                             f"{rb['view'].metric} ({rb['view'].select}): their scores cannot be compared")
    view: ScoreView = ra["view"]
    folder = Path(out) if out is not None else a.parent / f"compare-{a.name}-vs-{b.name}"
    folder.mkdir(parents=True, exist_ok=True)
    la, lb = sa.get("label", a.name), sb.get("label", b.name)
    table_rows = compare_rows(ra, rb)
    diff = config_diff(a, b)
    per_class = view.per_class if ra["class_scores"] and rb["class_scores"] else None
    classes, lacking = class_rows(sa, ra, sb, rb, view) if per_class else ([], None)
    if console is not None:
        from rich.table import Table

        t = Table(title=f"{la} (A) vs {lb} (B) — {ra['split']} split; 'best' = best validation {view.main[1]}")
        for col in ("score", f"A: {a.name}", f"B: {b.name}", "B − A"):
            t.add_column(col, justify="left" if col == "score" else "right")
        for r in table_rows:
            t.add_row(*r)
        console.print(t)
        for k, va, vb in diff[:20]:
            console.print(f"  differs: {k}: {va} → {vb}")
        if lacking:
            console.print(f"[yellow]{lacking}[/]", highlight=False)
    lines = [f"# {la} (A) vs {lb} (B)", "", f"A: `{a}`  ", f"B: `{b}`", "",
             f"## Scores ({ra['split']} split, {view.title})", "",
             f"'best' = the checkpoint with the best validation {view.main[1]} (A: step {ra['best_step']}, B: step "
             f"{rb['best_step']}); 'last' = the final step. One run each: a difference here is one draw, not an "
             "effect (`distilkit sweep` gives seeds and intervals).", "",
             "| score | A | B | B − A |", "|---|---|---|---|", *[f"| {' | '.join(r)} |" for r in table_rows], "",
             "## Configuration that differs", ""]
    lines += (["| key | A | B |", "|---|---|---|", *[f"| {k} | {va} | {vb} |" for k, va, vb in diff]]
              if diff else ["(none: the two runs have the same resolved configuration)"])
    lines.append("")
    if per_class:
        _, name, scale = per_class
        lines += [f"## Per-class {name} (best checkpoint)", "", *([f"Note: {lacking}.", ""] if lacking else []),
                  "| class | A | B | B − A |", "|---|---|---|---|"]
        lines += [f"| {n} | {' | '.join(_class_cells(scale, va, vb))} |" for n, va, vb in classes]
        lines.append("")
    _plot(folder / "compare.png", a, b, sa, sb, ra, rb, la, lb, classes)
    lines += ["![loss, per-class scores and previews of A and B](compare.png)", ""]
    atomic_write_text(folder / "compare.md", "\n".join(lines))
    return folder / "compare.md"


def _plot(path: Path, a: Path, b: Path, sa: dict[str, Any], sb: dict[str, Any], ra: dict[str, Any],
          rb: dict[str, Any], la: str, lb: str, classes: list[tuple[str, float, float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    view: ScoreView = ra["view"]
    pa, pb = plots.read_preview(a), plots.read_preview(b)
    n_rows = 1 + (pa is not None and pb is not None)
    fig = plt.figure(figsize=(15, 4.5 * n_rows))
    ax1 = fig.add_subplot(n_rows, 2, 1)
    plots.loss_curves(ax1, plots.task_loss(plots.read_log(a)[0]), prefix="A ", style="-")
    plots.loss_curves(ax1, plots.task_loss(plots.read_log(b)[0]), prefix="B ", style="--")
    ax1.set_title("task loss, without distillation terms (A solid, B dashed)")
    ax2 = fig.add_subplot(n_rows, 2, 2)
    if view.per_class is not None and classes:
        colour = {**dict(zip(*class_table(sb, view))), **dict(zip(*class_table(sa, view)))}  # A's where both
        s = view.per_class[2]
        plots.class_bars(ax2, [n for n, _, _ in classes], [colour[n] for n, _, _ in classes],
                         [[s * va for _, va, _ in classes], [s * vb for _, _, vb in classes]],  # NaN: no bar
                         [f"A {la}", f"B {lb} (hatched)"], f"{view.per_class[1]} (best checkpoint)")
    else:
        cols = view.headline
        ax2.bar([f"A {c[1]}" for c in cols] + [f"B {c[1]}" for c in cols],
                [c[2] * ra["best"][c[0]] for c in cols] + [c[2] * rb["best"][c[0]] for c in cols])
        ax2.set_title("best checkpoint")
    if pa is not None and pb is not None:
        for i, (p, who) in enumerate(((pa, "A"), (pb, "B"))):
            ax = fig.add_subplot(n_rows, 2, 3 + i)
            plots.bev_panel(ax, p["prediction"], p["extent"], p.get("class_colours", np.zeros((0, 3))),
                            f"{who}: prediction from above")
    plots.save(fig, path)


__all__ = ["compare_runs", "config_diff"]
