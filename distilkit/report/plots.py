"""The plots of run reports (matplotlib, Agg): loss curves per term, per-class scores, bird's-eye previews.

Each function draws onto axes it is given, so a run's report and a comparison of runs share them; files are
written through :func:`save` (a temporary file renamed over the target: never half a PNG).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

NOT_TERMS = {"step", "event", "grad_norm", "lr", "time", "epoch"}


def short(label: str, most: int = 40) -> str:
    """A label as a plot shows it: at most ``most`` characters (matplotlib lays out and renders every glyph of a tick
    label or legend entry, so a long one costs seconds; the tables carry it whole)."""
    return label if len(label) <= most else label[: most - 1] + "…"


def figure(ncols: int, width: float = 5.0, height: float = 4.0) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(width * ncols, height), squeeze=False)
    return fig, axes[0]


def save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.tight_layout(rect=(0.0, getattr(fig, "distilkit_bottom", 0.0), 1.0, 1.0))  # a figure legend keeps its room
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path


def read_log(run_dir: Path) -> tuple[dict[str, tuple[list[int], list[float]]], dict[str, tuple[list[int], list[float]]]]:
    """From ``metrics.jsonl``: each training term's (steps, values) and each validation score's (steps, values).
    A line cut by a kill is skipped."""
    terms: dict[str, tuple[list[int], list[float]]] = {}
    val: dict[str, tuple[list[int], list[float]]] = {}
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        return terms, val
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue
        step = rec.get("step")
        if not isinstance(step, int):
            continue
        if isinstance(rec.get("eval"), dict):
            scores, target = rec["eval"], val
        elif "loss" in rec and "event" not in rec:
            scores, target = {k: v for k, v in rec.items() if k not in NOT_TERMS}, terms
        else:
            continue
        for k, v in scores.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
                xs, ys = target.setdefault(k, ([], []))
                xs.append(step)
                ys.append(float(v))
    return terms, val


def loss_curves(ax: Any, terms: dict[str, tuple[list[int], list[float]]], prefix: str = "", style: str = "-") -> None:
    """The total loss and every weighted term (log scale where all are positive)."""
    for k, (xs, ys) in terms.items():
        ax.plot(xs, ys, style, label=f"{prefix}{k}", linewidth=2.0 if k == "loss" else 1.0)
    positive = all(y > 0 for _, ys in terms.values() for y in ys)
    if terms and positive:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("weighted term (training batch)")
    ax.set_title("loss per term")
    if terms:
        ax.legend(fontsize=7)
    elif not ax.lines:
        ax.text(0.5, 0.5, "no loss logged: the run is shorter than train.log_every", ha="center", va="center",
                transform=ax.transAxes, fontsize=8, color="gray")


def class_bars(ax: Any, names: list[str], colours: list[tuple[int, int, int]], values: list[list[float]],
               labels: list[str], what: str) -> None:
    """Per-class scores as bars in the classes' colours, one group of bars per run (hatched for later runs)."""
    n = len(values)
    width = 0.8 / max(n, 1)
    x = np.arange(len(names))
    for i, (vals, label) in enumerate(zip(values, labels)):
        ax.bar(x + (i - (n - 1) / 2) * width, vals, width, color=[np.array(c) / 255 for c in colours],
               edgecolor="black", linewidth=0.4, hatch=None if i == 0 else "//", label=label)
    ax.set_xticks(x, names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(what)
    if n > 1:  # above the plot, where it covers no bar
        ax.legend(fontsize=7, loc="lower left", bbox_to_anchor=(0.0, 1.01), ncol=n, frameon=False)


def task_loss(terms: dict[str, tuple[list[int], list[float]]]) -> dict[str, tuple[list[int], list[float]]]:
    """The logged total minus the distillation terms (``kd_*``): what runs with and without distillation optimise
    alike."""
    if "loss" not in terms:
        return {}
    steps, total = terms["loss"]
    kd = [dict(zip(*v)) for k, v in terms.items() if k.startswith("kd_")]
    return {"task loss": (steps, [t - sum(d.get(s, 0.0) for d in kd) for s, t in zip(steps, total)])}


def bev_panel(ax: Any, value: np.ndarray, extent: np.ndarray, colours: np.ndarray, title: str) -> None:
    """One bird's-eye panel: a class-id image (x forward up, y left to the left) or a point cloud coloured by
    height; or an (H, W, 3) camera image as it is."""
    x0, x1, y0, y1 = (float(v) for v in extent)
    if value.ndim == 3 and value.shape[-1] == 3:  # a camera image, shown as the camera saw it
        ax.imshow(value, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
        return
    if value.ndim == 2 and np.issubdtype(value.dtype, np.integer):
        rgb = np.ones(value.shape + (3,), dtype=np.float32)  # white where nothing is
        known = (value >= 0) & (value < len(colours))
        rgb[known] = colours[value[known]] / 255.0
        # image rows = x (forward, up), columns = y (left to the left): flip both so the view is a map
        ax.imshow(rgb[::-1, ::-1], extent=(y1, y0, x0, x1), interpolation="nearest")
    else:
        pts = np.asarray(value, dtype=np.float32)
        if len(pts):
            ax.scatter(pts[:, 1], pts[:, 0], c=pts[:, 2] if pts.shape[1] > 2 else None, s=0.3, cmap="viridis",
                       linewidths=0)
        ax.set_xlim(y1, y0)
        ax.set_ylim(x0, x1)
        ax.set_aspect("equal")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("y (m, left)")
    ax.set_ylabel("x (m, forward)")


def read_preview(run_dir: Path) -> dict[str, np.ndarray] | None:
    """``preview.npz`` of a run (arrays only: read without pickle), or None."""
    path = run_dir / "preview.npz"
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError):
        return None


def bev_row(axes: list[Any], preview: dict[str, np.ndarray], title: str = "", model_input: str = "") -> None:
    """Input, prediction and ground truth from above, with a legend of the classes they show (a class-id panel's
    colours). ``model_input``: what the model reads (the results table's input column, e.g. "4 frames"), said under
    the input panel, which shows the current scan (or image) only."""
    colours = preview.get("class_colours", np.zeros((0, 3)))
    for ax, key in zip(axes, ("input", "prediction", "target")):
        if key in preview:
            name = {"input": "input image" if preview[key].ndim == 3 else "input: the current scan",
                    "prediction": "prediction", "target": "ground truth"}[key]
            if key == "input" and model_input:
                name += f"\n(the model reads {model_input})"
            bev_panel(ax, preview[key], preview["extent"], colours, f"{title}{name}")
        else:
            ax.set_axis_off()
    class_legend(axes[-1].figure, preview)


def class_legend(fig: Any, preview: dict[str, np.ndarray]) -> None:
    """A legend of the classes the class-id panels show, in their colours, under the figure."""
    from matplotlib.patches import Patch

    names, colours = preview.get("class_names"), preview.get("class_colours")
    if names is None or colours is None:
        return
    shown = sorted({int(c) for key in ("prediction", "target") if key in preview
                    and preview[key].ndim == 2 and np.issubdtype(preview[key].dtype, np.integer)
                    for c in np.unique(preview[key]) if 0 <= c < len(names)})
    if not shown:
        return
    handles = [Patch(facecolor=np.asarray(colours[c]) / 255.0, edgecolor="black", linewidth=0.3, label=str(names[c]))
               for c in shown]
    fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 7), fontsize=7, frameon=False)
    fig.distilkit_bottom = 0.05 * ((len(handles) - 1) // 7 + 1)  # room kept under the axes by save()


__all__ = ["bev_panel", "bev_row", "class_bars", "figure", "loss_curves", "read_log", "read_preview", "save",
           "task_loss"]
