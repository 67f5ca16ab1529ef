"""Progress bars, the final comparison table, and the Markdown + PNG report of a run."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any, Callable, Iterator

from distilkit.engine.io import atomic_write_text


@contextlib.contextmanager
def stage_progress(console: Any, name: str) -> Iterator[Callable[[int, int, dict[str, float]], None]]:
    """A rich progress bar for one stage: steps, it/s, ETA and the current loss terms."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    columns = [TextColumn(f"[bold cyan]{name}[/]"), BarColumn(), MofNCompleteColumn(),
               TextColumn("{task.fields[rate]}"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
               TextColumn("{task.fields[terms]}")]
    with Progress(*columns, console=console, transient=False) as progress:
        task = progress.add_task(name, total=None, rate="", terms="")
        state = {"t0": None, "s0": 0}

        def on_step(step: int, total: int, values: dict[str, float]) -> None:
            import time

            now = time.perf_counter()
            if state["t0"] is None:
                state["t0"], state["s0"] = now, step - 1
            done = step - state["s0"]
            rate = done / max(now - state["t0"], 1e-9)
            terms = " ".join(f"{k}={v:.3g}" for k, v in values.items())
            progress.update(task, completed=step, total=total, rate=f"{rate:.2f} it/s", terms=terms)

        yield on_step


def _row(summary: dict[str, Any]) -> dict[str, Any]:
    """One stage's figures: test-split scores at the best-validation and the last checkpoint."""
    test = summary.get("test") or {}
    best = test.get("best") or summary.get("best", {}).get("scores") or summary.get("last") or {}
    last = test.get("last") or summary.get("last") or {}
    val = summary.get("best", {}).get("scores") or {}
    nan = float("nan")
    return {"stage": summary["stage"], "label": summary.get("label", summary["stage"]), "adapter": summary["adapter"],
            "input": summary.get("input", f"{summary['frames']} frames" if summary.get("frames") else ""),
            "teacher": summary.get("teacher") or "—",
            "objectives": ", ".join(summary.get("objectives", [])) or "—", "miou": best.get("miou", nan),
            "iou": best.get("iou", nan), "precision": best.get("precision", nan), "recall": best.get("recall", nan),
            "best_step": test.get("best_step", summary.get("best", {}).get("step")),
            "last_miou": last.get("miou", nan), "last_iou": last.get("iou", nan), "val_miou": val.get("miou", nan),
            "steps": summary.get("steps"), "class_iou": best.get("class_iou", []),
            "split": summary.get("report_split", "val")}


def _header(rows: list[dict[str, Any]]) -> str:
    split = rows[0]["split"] if rows else "test"
    return (f"{split} split, SSC metrics in %: 'best' = the checkpoint with the best validation mIoU (its step "
            f"shown), 'last' = the final step")


def results_table(results: list[Any]) -> Any:
    from rich.table import Table

    rows = [_row(r.summary) for r in results]
    table = Table(title=f"distilkit results — {_header(rows)}")
    cols = ("stage", "model", "input", "teacher", "distillation", "mIoU best", "IoU best", "best step",
            "mIoU last", "IoU last", "val mIoU", "")
    for col in cols:
        table.add_column(col, justify="left" if col in ("stage", "model", "input", "teacher", "distillation", "") else "right")
    for r, row in zip(results, rows):
        table.add_row(row["label"], row["adapter"], row["input"], row["teacher"], row["objectives"],
                      f"{100 * row['miou']:.2f}", f"{100 * row['iou']:.2f}", str(row["best_step"]),
                      f"{100 * row['last_miou']:.2f}", f"{100 * row['last_iou']:.2f}", f"{100 * row['val_miou']:.2f}",
                      "reused" if r.reused else "trained")
    return table


def _losses(run_dir: Path) -> tuple[list[int], list[float]]:
    steps, losses = [], []
    path = run_dir / "metrics.jsonl"
    if path.is_file():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if "loss" in rec:  # the task loss: the total without distillation terms
                steps.append(rec["step"])
                losses.append(rec["loss"] - sum(v for k, v in rec.items() if k.startswith("kd_")))
    return steps, losses


def write_report(pipeline: Any, results: list[Any]) -> Path:
    """Print the comparison table and write ``report.md`` and ``report.png`` beside the stage folders."""
    pipeline.console.print(results_table(results))
    root: Path = pipeline.root
    rows = [_row(r.summary) for r in results]
    lines = [f"# {pipeline.recipe.name}", "", f"Seed {pipeline.recipe.seed}; {_header(rows)}.", "",
             "| stage | model | input | teacher | distillation | mIoU best | IoU best | precision | recall | best step "
             "| mIoU last | IoU last | val mIoU | run |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r, row in zip(results, rows):
        lines.append(f"| {row['label']} | {row['adapter']} | {row['input']} | {row['teacher']} | {row['objectives']} | "
                     f"{100 * row['miou']:.2f} | {100 * row['iou']:.2f} | {100 * row['precision']:.2f} | "
                     f"{100 * row['recall']:.2f} | {row['best_step']} | {100 * row['last_miou']:.2f} | "
                     f"{100 * row['last_iou']:.2f} | {100 * row['val_miou']:.2f} | {'reused' if r.reused else 'trained'} |")
    lines += ["", "## Per-class IoU (%, best checkpoint)", "", "| class | " + " | ".join(r["label"] for r in rows) + " |",
              "|---|" + "---|" * len(rows)]
    for c, cname in enumerate(pipeline.resolved.data_info.class_names[1:]):
        vals = [f"{100 * r['class_iou'][c]:.1f}" if len(r["class_iou"]) > c else "—" for r in rows]
        lines.append(f"| {cname} | " + " | ".join(vals) + " |")
    lines += ["", "![training loss and validation mIoU](report.png)", ""]
    atomic_write_text(root / "report.md", "\n".join(lines))
    try:
        _plot(root / "report.png", results, rows)
    except Exception as exc:  # a plotting problem must not lose a finished run
        pipeline.console.print(f"[yellow]report.png not written: {exc}[/]")
    pipeline.console.print(f"report: {root / 'report.md'}")
    return root / "report.md"


def _plot(path: Path, results: list[Any], rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for r in results:
        steps, losses = _losses(r.run_dir)
        if steps:
            ax1.plot(steps, losses, label=r.summary.get("label", r.name))
    ax1.set_xlabel("step")
    ax1.set_ylabel("task loss (without distillation terms)")
    ax1.set_yscale("log")
    ax1.legend(fontsize=8)
    ax1.set_title("training loss")
    labels = [r["label"] for r in rows]
    ax2.bar(labels, [100 * r["miou"] for r in rows], color="tab:blue", label="mIoU")
    ax2.plot(labels, [100 * r["iou"] for r in rows], "o", color="tab:orange", label="completion IoU")
    ax2.set_ylabel("%")
    ax2.set_title(f"{rows[0]['split'] if rows else 'test'} split, best-validation checkpoint")
    ax2.legend(fontsize=8)
    ax2.tick_params(axis="x", rotation=20)
    fig.tight_layout()
    tmp = path.with_name(".report.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
