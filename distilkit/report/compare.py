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
    return f"{col[2] * d:+.2f}" if col[2] != 1.0 else f"{d:+.4g}"


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
    if view.per_class is not None and ra["class_scores"] and rb["class_scores"]:
        _, name, scale = view.per_class
        names, _ = class_table(sa, view)
        lines += [f"## Per-class {name} (best checkpoint)", "", "| class | A | B | B − A |", "|---|---|---|---|"]
        for n, va, vb in zip(names, ra["class_scores"], rb["class_scores"]):
            lines.append(f"| {n} | {scale * va:.1f} | {scale * vb:.1f} | {scale * (vb - va):+.1f} |")
        lines.append("")
    _plot(folder / "compare.png", a, b, sa, ra, rb, la, lb)
    lines += ["![loss, per-class scores and previews of A and B](compare.png)", ""]
    atomic_write_text(folder / "compare.md", "\n".join(lines))
    return folder / "compare.md"


def _plot(path: Path, a: Path, b: Path, sa: dict[str, Any], ra: dict[str, Any], rb: dict[str, Any], la: str,
          lb: str) -> None:
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
    if view.per_class is not None and ra["class_scores"] and rb["class_scores"]:
        names, colours = class_table(sa, view)
        k = min(len(names), len(ra["class_scores"]), len(rb["class_scores"]))
        s = view.per_class[2]
        plots.class_bars(ax2, names[:k], colours[:k], [[s * v for v in ra["class_scores"][:k]],
                                                       [s * v for v in rb["class_scores"][:k]]],
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
