"""One recipe run with several training seeds: mean ± sample std per stage and paired differences.

Each seed is its own run (its own stage folders); this module only reads their summaries. Scores are the
test split at the best-validation checkpoint (and at the last step). The paired difference of a stage to
the baseline stage is taken seed by seed (same scenes, same seed), which removes the part of the spread
the two share; a method "helps" here only when the mean difference is clearly larger than its spread.
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

from distilkit.engine.io import atomic_write_text
from distilkit.errors import DistilkitError
from distilkit.engine.report import _row


def default_baseline(resolved: Any) -> str | None:
    """The first stage without distillation that no other stage uses as its teacher (the plain student)."""
    teachers = {s.teacher_from for s in resolved.stages.values() if s.teacher_from}
    for name in resolved.order:
        if not resolved.stages[name].distill and name not in teachers:
            return name
    return None


def _mean_std(xs: list[float]) -> tuple[float, float]:
    return statistics.fmean(xs), statistics.stdev(xs) if len(xs) > 1 else math.nan


def seed_rows(results_by_seed: dict[int, list[Any]], baseline: str | None) -> list[dict[str, Any]]:
    """Per stage (recipe order): seeds, per-seed test mIoU / IoU (best-val and last checkpoints), their
    mean and sample std, and the per-seed differences in mIoU to ``baseline`` with their mean and std."""
    seeds = sorted(results_by_seed)
    per_stage: dict[str, dict[int, dict[str, Any]]] = {}
    for seed in seeds:
        for result in results_by_seed[seed]:
            per_stage.setdefault(result.name, {})[seed] = _row(result.summary)
    base = per_stage.get(baseline or "", {})
    rows = []
    for name, by_seed in per_stage.items():
        got = sorted(by_seed)
        row: dict[str, Any] = {"stage": name, "label": by_seed[got[0]]["label"], "seeds": got,
                               "objectives": by_seed[got[0]]["objectives"]}
        for key in ("miou", "iou", "last_miou"):
            values = [by_seed[s][key] for s in got]
            row[key] = values
            row[f"{key}_mean"], row[f"{key}_std"] = _mean_std(values)
        paired = [by_seed[s]["miou"] - base[s]["miou"] for s in got if s in base] if base and name != baseline else []
        row["delta"] = paired
        row["delta_mean"], row["delta_std"] = _mean_std(paired) if paired else (math.nan, math.nan)
        rows.append(row)
    return rows


def _pm(mean: float, std: float, sign: str = "") -> str:
    value = f"{100 * mean:{sign}.2f}"
    return value if math.isnan(std) else f"{value} ± {100 * std:.2f}"


def _deltas(row: dict[str, Any]) -> tuple[str, str]:
    if not row["delta"]:
        return "—", "—"
    return " / ".join(f"{100 * d:+.2f}" for d in row["delta"]), _pm(row["delta_mean"], row["delta_std"], "+")


def seeds_table(rows: list[dict[str, Any]], baseline: str | None) -> Any:
    from rich.table import Table

    seeds = sorted({s for r in rows for s in r["seeds"]})
    table = Table(title=f"distilkit seeds {', '.join(map(str, seeds))} — test split, mean ± std over seeds, "
                        f"'best' = best-validation checkpoint; Δ = paired difference to '{baseline or '—'}'")
    for col in ("stage", "distillation", "mIoU best", "IoU best", "mIoU last", "Δ mIoU per seed", "Δ mIoU"):
        table.add_column(col, justify="left" if col in ("stage", "distillation") else "right")
    for row in rows:
        per_seed, mean = _deltas(row)
        table.add_row(row["label"], row["objectives"], _pm(row["miou_mean"], row["miou_std"]),
                      _pm(row["iou_mean"], row["iou_std"]), _pm(row["last_miou_mean"], row["last_miou_std"]),
                      per_seed, mean)
    return table


def write_seeds_report(root: Path, rows: list[dict[str, Any]], baseline: str | None, console: Any) -> Path:
    """Print the table and write ``seeds.md`` (and ``seeds.png``: each seed as a dot, the mean as a bar)."""
    console.print(seeds_table(rows, baseline))
    seeds = sorted({s for r in rows for s in r["seeds"]})
    lines = [f"# {root.name}: seeds {', '.join(map(str, seeds))}", "",
             "Test split, SSC metrics in %, mean ± sample std over the seeds; 'best' = the checkpoint with the best "
             f"validation mIoU, 'last' = the final step. Δ = the paired difference in test mIoU to "
             f"'{baseline or '—'}', seed by seed.", "",
             "| stage | distillation | seeds | mIoU best | IoU best | mIoU last | Δ mIoU per seed | Δ mIoU |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        per_seed, mean = _deltas(row)
        lines.append(f"| {row['label']} | {row['objectives']} | {','.join(map(str, row['seeds']))} | "
                     f"{_pm(row['miou_mean'], row['miou_std'])} | {_pm(row['iou_mean'], row['iou_std'])} | "
                     f"{_pm(row['last_miou_mean'], row['last_miou_std'])} | {per_seed} | {mean} |")
    lines += ["", "![test mIoU per seed](seeds.png)", ""]
    path = root / "seeds.md"
    atomic_write_text(path, "\n".join(lines))
    try:
        _plot(root / "seeds.png", rows)
    except Exception as exc:  # a plotting problem must not lose the table
        console.print(f"[yellow]seeds.png not written: {exc}[/]")
    console.print(f"seeds report: {path}")
    return path


def _plot(path: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(rows) + 2), 4.0))
    for i, row in enumerate(rows):
        ax.bar(i, 100 * row["miou_mean"], color="#9ecae1", yerr=None if math.isnan(row["miou_std"]) else
               100 * row["miou_std"], capsize=3)
        ax.scatter([i] * len(row["miou"]), [100 * v for v in row["miou"]], color="#08519c", s=12, zorder=3)
    ax.set_xticks(range(len(rows)), [r["label"] for r in rows], rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("test mIoU (%), best-val checkpoint")
    ax.set_title("mean ± std over seeds; dots: single seeds")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_seeds(recipe: str | Path, output: str | Path, seeds: list[int], baseline: str | None = None,
              quiet: bool = False, rerun: list[str] | None = None) -> list[dict[str, Any]]:
    """Run the recipe once per seed (finished stages are reused), then report mean ± std over the seeds."""
    from distilkit.engine.pipeline import Pipeline

    if len(set(seeds)) != len(seeds):
        raise DistilkitError(f"--seed: give each seed once, got {' '.join(map(str, seeds))}")
    results: dict[int, list[Any]] = {}
    pipe = None
    for seed in seeds:
        pipe = Pipeline(recipe, output, quiet=quiet, seed=seed)
        if baseline is not None:
            pipe.check_stages("--baseline", [baseline])
        if not quiet:
            pipe.console.rule(f"seed {seed}")
        results[seed] = pipe.run(rerun=rerun)
    assert pipe is not None
    chosen = baseline if baseline is not None else default_baseline(pipe.resolved)
    rows = seed_rows(results, chosen)
    write_seeds_report(pipe.root, rows, chosen, pipe.console)
    return rows
