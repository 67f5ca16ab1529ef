"""Where each method helps (issue 59, item 4): each method's paired difference in per-class IoU to the baseline.

mIoU is the mean of the classes' IoUs, and the rare classes move most: a method that lifts two rare classes and
costs the road reads as +1 mIoU. For each method of the table's family (each at its validation-chosen weight,
:func:`~distilkit.report.family.family`) and each class, the per-seed differences of the class's IoU to the
baseline's on the same seed, their mean and 95 % Student-t interval over the seeds; the classes ordered by how many
ground-truth voxels of the split they have (``class_voxels``, most first; in the data's order for runs that did not
record it). Written as ``<stem>_classes.md`` and a heat map ``<stem>_classes.png`` (classes × methods, the colour the
mean difference, ``+``/``−`` where the interval excludes 0). These are one interval per cell, not corrected for the
many cells: they locate an effect the family's corrected figures found, they do not claim new ones.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from distilkit.files import atomic_write_text
from distilkit.report import family
from distilkit.report.multiple import t_interval


def class_table(rows: list[dict[str, Any]], baseline: str | None) -> dict[str, Any] | None:
    """``classes`` (ordered), ``voxels`` (their share of the split's labelled voxels, None where unknown) and, per
    method label, a list of (mean, low, high) per class in that order (None: nothing to compare per class)."""
    base = next((r for r in rows if r["stage"] == baseline), None)
    members = [r for r in family.family(rows) or [r for r in rows if r["delta"]] if r.get("class_iou")]
    if base is None or not base.get("class_iou") or not members or not base.get("class_names"):
        return None
    names = list(base["class_names"])
    counts = base.get("class_voxels") or []
    order = sorted(range(len(names)), key=lambda c: -counts[c]) if len(counts) == len(names) else list(range(len(names)))
    total = sum(counts) if len(counts) == len(names) else 0
    out: dict[str, list[tuple[float, float, float]]] = {}
    shared: dict[str, int] = {}  # each method's count of seeds it shares with the baseline
    for row in members:
        seeds = [s for s in row["class_iou"] if s in base["class_iou"]]
        shared[row["label"]] = len(seeds)
        cells = []
        for c in order:
            d = [row["class_iou"][s][c] - base["class_iou"][s][c] for s in seeds]
            cells.append((sum(d) / len(d) if d else math.nan, *t_interval(d)))
        out[row["label"]] = cells
    return {"classes": [names[c] for c in order], "voxels": [counts[c] / total for c in order] if total else None,
            "methods": out, "seeds": shared, "scale": base["view"].per_class[2]
            if base["view"].per_class else 1.0}


def _cell(mean: float, low: float, high: float, scale: float) -> str:
    if math.isnan(mean):
        return "—"
    text = f"{scale * mean:+.1f}"
    if math.isnan(low):
        return text
    text += f" [{scale * low:+.1f}, {scale * high:+.1f}]"
    return f"**{text}**" if low > 0 or high < 0 else text


def classes_markdown(table: dict[str, Any], title: str, image: str | None) -> str:
    """The per-class table: a row a class (with its share of the voxels), a column a method."""
    methods, scale = list(table["methods"]), table["scale"]
    share, counts = table["voxels"], table["seeds"]
    if len(set(counts.values())) <= 1:  # every method over as many seeds: said once
        over, heads = f"{next(iter(counts.values()), 0)} seeds", methods
    else:  # a sweep not finished: each column says how many seeds its mean is over
        over = (f"the seeds each method shares with the baseline ({min(counts.values())} to "
                f"{max(counts.values())}: the count follows each column's name)")
        heads = [f"{m} ({counts[m]})" for m in methods]
    lines = [f"# {title}: per class", "",
             f"Each method's paired difference in per-class IoU to the baseline (points), mean over {over} "
             "with its 95 % Student-t interval; bold where the interval excludes 0. One interval per cell, "
             "not corrected for the many cells: read them for where a method's effect lies, not as claims. "
             + ("Classes ordered by their share of the split's labelled voxels." if share else
                "Classes in the data's order (these runs did not record each class's voxels)."), "",
             "| class | " + ("voxels | " if share else "") + " | ".join(heads) + " |",
             "|---|" + ("---|" if share else "") + "---|" * len(methods)]
    for i, name in enumerate(table["classes"]):
        cells = [_cell(*table["methods"][m][i], scale) for m in methods]
        lines.append(f"| {name} | " + (f"{100 * share[i]:.2f} % | " if share else "") + " | ".join(cells) + " |")
    if image:
        lines += ["", f"![per-class differences: classes x methods]({image})"]
    return "\n".join(lines + [""])


def plot_classes(path: Path, table: dict[str, Any]) -> None:
    """The heat map: classes (rows, most voxels on top) × methods, the mean difference's colour on a scale symmetric
    about 0, ``+``/``−`` where the interval excludes 0."""
    import numpy as np

    from distilkit.report import plots

    methods, classes, scale = list(table["methods"]), table["classes"], table["scale"]
    values = np.array([[scale * table["methods"][m][i][0] for m in methods] for i in range(len(classes))])
    fig, (ax,) = plots.figure(1, width=max(5.0, 0.9 * len(methods) + 3), height=max(3.0, 0.32 * len(classes) + 1.6))
    bound = float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0
    image = ax.imshow(values, cmap="RdBu", vmin=-bound, vmax=bound, aspect="auto")
    for i in range(len(classes)):
        for j, m in enumerate(methods):
            _, low, high = table["methods"][m][i]
            if not math.isnan(low) and (low > 0 or high < 0):
                ax.text(j, i, "+" if low > 0 else "−", ha="center", va="center", fontsize=9, color="black")
    ax.set_xticks(range(len(methods)), [plots.short(m, 30) for m in methods], rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(len(classes)), classes, fontsize=8)
    fig.colorbar(image, ax=ax, label="Δ IoU (points), mean over seeds")
    ax.set_title("paired Δ IoU per class; +/−: 95 % interval excludes 0 (uncorrected)", fontsize=9)
    plots.save(fig, path)


def write_classes(root: Path, stem: str, rows: list[dict[str, Any]], baseline: str | None, title: str,
                  console: Any) -> Path | None:
    """``<stem>_classes.md`` and ``<stem>_classes.png`` where the rows have per-class scores (else nothing)."""
    table = class_table(rows, baseline)
    if table is None:
        return None
    path = root / f"{stem}_classes.md"
    atomic_write_text(path, classes_markdown(table, title, f"{stem}_classes.png"))
    try:
        plot_classes(root / f"{stem}_classes.png", table)
    except Exception as exc:  # a plotting problem must not lose the table
        console.print(f"[yellow]{stem}_classes.png not written: {exc}[/]")
    return path


__all__ = ["class_table", "classes_markdown", "plot_classes", "write_classes"]
