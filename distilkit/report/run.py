"""One stage run's report: ``report.md`` in its folder with ``loss.png`` (every term over the steps, and the
validation score), ``classes.png`` (per-class scores at the best checkpoint) and ``bev.png`` (input, prediction
and ground truth of a validation scene from above, in the dataset's class colours).

Everything is drawn from the files of the run folder — ``summary.json``, ``metrics.jsonl``, ``preview.npz``,
``recipe.resolved.yaml`` — so ``distilkit report RUN_DIR`` re-renders it without data or a model.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import yaml

from distilkit.files import atomic_write_text
from distilkit.report.scores import ScoreView, stage_row
from distilkit.errors import DistilkitError
from distilkit.report import plots


def waited(summary: dict[str, Any]) -> str:
    """``" (W s of it waiting for the loader's batches)"`` where the summary records it (older runs do not)."""
    wait = summary.get("input_wait_seconds")
    return "" if wait is None else f" ({wait:g} s of it waiting for the loader's batches)"


def read_run(run_dir: str | Path) -> tuple[Path, dict[str, Any]]:
    """A finished run's folder and summary; a clear error for anything else."""
    path = Path(run_dir)
    summary_path = path / "summary.json"
    if not summary_path.is_file():
        hint = ""
        if path.is_dir() and any(path.glob("*/summary.json")):
            hint = f" (it holds stage runs: {', '.join(sorted(p.parent.name for p in path.glob('*/summary.json')))})"
        raise DistilkitError(f"{path}: not a finished stage run — no summary.json{hint}")
    try:
        summary = json.loads(summary_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DistilkitError(f"{summary_path}: unreadable ({exc})") from None
    if not isinstance(summary, dict) or "stage" not in summary:
        raise DistilkitError(f"{summary_path}: not a distilkit run summary")
    return path, summary


def class_table(summary: dict[str, Any], view: ScoreView) -> tuple[list[str], list[tuple[int, int, int]]]:
    """The per-class rows' names and colours (from the summary, else SemanticKITTI's table)."""
    from distilkit.data.classes import CLASS_COLOURS, CLASS_NAMES

    classes = summary.get("classes") or {"names": CLASS_NAMES, "colours": CLASS_COLOURS}
    names, colours = list(classes["names"]), [tuple(c) for c in classes["colours"]]
    return names[view.first_class:], colours[view.first_class:]


def scores_lines(row: dict[str, Any], view: ScoreView) -> list[str]:
    lines = [f"| score | best (step {row['best_step']}) | last (step {row['steps']}) |", "|---|---|---|"]
    for col in view.columns:
        lines.append(f"| {col[1]} | {view.fmt(col, row['best'][col[0]])} | {view.fmt(col, row['last'][col[0]])} |")
    return lines


def write_run_report(run_dir: str | Path) -> Path:
    """Write (or re-render) ``report.md`` and its PNGs in a finished stage run's folder."""
    path, summary = read_run(run_dir)
    row = stage_row(summary)
    view: ScoreView = row["view"]
    resolved: dict[str, Any] = {}
    if (path / "recipe.resolved.yaml").is_file():
        resolved = yaml.safe_load((path / "recipe.resolved.yaml").read_text(encoding="utf-8")) or {}
    terms, val = plots.read_log(path)
    fig, (ax1, ax2) = plots.figure(2)
    plots.loss_curves(ax1, terms)
    if view.select in val:
        xs, ys = val[view.select]
        ax2.plot(xs, [view.main[2] * y for y in ys], "o-")
    ax2.set_xlabel("step")
    ax2.set_ylabel(f"validation {view.main[1]}")
    ax2.set_title(f"validation {view.main[1]} (selects best.pt)")
    plots.save(fig, path / "loss.png")
    images = ["loss.png"]
    lines = [f"# {summary.get('label', summary['stage'])}", "",
             f"Stage `{summary['stage']}` of recipe `{resolved.get('recipe', '?')}`, run `{path.name}`: "
             f"{summary.get('adapter', '?')} ({summary.get('input', '')}), teacher {summary.get('teacher') or '—'}, "
             f"distillation {', '.join(summary.get('objectives', [])) or '—'}; seed {summary.get('seed', '?')}, "
             f"{summary.get('steps', '?')} steps in {summary.get('train_seconds', '?')} s"
             f"{waited(summary)}.", "",
             f"## Scores ({row['split']} split, {view.title})", "",
             f"'best' = the checkpoint with the best validation {view.main[1]}"
             f"{' (lowest)' if view.lower_is_better else ''}; 'last' = the final step.", "",
             *scores_lines(row, view), "", "## Training", "", "![loss per term and validation score](loss.png)", ""]
    if view.per_class is not None and row["class_scores"]:
        key, name, scale = view.per_class
        names, colours = class_table(summary, view)
        values = [scale * v for v in row["class_scores"]][: len(names)]
        fig, (ax,) = plots.figure(1, width=8.0)
        plots.class_bars(ax, names[: len(values)], colours[: len(values)], [values], [summary.get("label", "")],
                         f"{row['split']} {name}{' (%)' if scale == 100 else ''}, best checkpoint")
        plots.save(fig, path / "classes.png")
        images.append("classes.png")
        lines += [f"## Per-class {name} (best checkpoint)", "", "| class | " + name + " |", "|---|---|"]
        lines += [f"| {n} | {v:.1f} |" for n, v in zip(names, values)]
        lines += ["", f"![per-class {name}](classes.png)", ""]
    preview = plots.read_preview(path)
    if preview is not None:
        fig, axes = plots.figure(3, width=4.5, height=4.5)
        plots.bev_row(list(axes), preview, model_input=str(summary.get("input") or ""))
        plots.save(fig, path / "bev.png")
        lines += ["## A validation scene from above", "",
                  f"The first validation scene at the best checkpoint (step {int(preview.get('step', -1))}): the input "
                  "(scan, or a camera model's image), the prediction and the ground truth, seen from above (voxels: the class of the highest "
                  "occupied voxel of each column, in the dataset's colours; points: coloured by height).", "",
                  "![input, prediction and ground truth from above](bev.png)", ""]
    atomic_write_text(path / "report.md", "\n".join(lines))
    return path / "report.md"


def report_targets(path: str | Path) -> list[Path]:
    """A stage run folder, or every finished stage run under a folder at any depth (a recipe's output folder, a
    sweep's, or ``runs/`` holding several): a folder with ``summary.json`` is a run and is not searched further."""
    p = Path(path)
    if (p / "summary.json").is_file():
        return [p]
    if not p.is_dir():
        raise DistilkitError(f"{p}: no such folder (give a stage run folder or a folder of runs)")
    found: list[Path] = []
    for folder, subfolders, files in os.walk(p):
        if "summary.json" in files:
            found.append(Path(folder))
            subfolders.clear()  # a run's own folders (checkpoints, predictions) hold no other run
        else:
            subfolders[:] = [d for d in subfolders if not d.startswith(".")]
    if not found:
        raise DistilkitError(f"{p}: no finished stage run here or under it (a stage run folder holds summary.json)")
    return sorted(found)


__all__ = ["read_run", "report_targets", "write_run_report"]
