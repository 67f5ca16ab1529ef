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
from distilkit.engine.scores import ScoreView, stage_row


def default_baseline(resolved: Any) -> str | None:
    """The first stage without distillation that no other stage uses as its teacher (the plain student)."""
    teachers = {s.teacher_from for s in resolved.stages.values() if s.teacher_from}
    for name in resolved.order:
        if not resolved.stages[name].distill and name not in teachers:
            return name
    return None


def _mean_std(xs: list[float]) -> tuple[float, float]:
    if any(math.isnan(x) for x in xs):  # a score a stage does not have
        return math.nan, math.nan
    return statistics.fmean(xs), statistics.stdev(xs) if len(xs) > 1 else math.nan


def seed_rows(results_by_seed: dict[int, list[Any]], baseline: str | None) -> list[dict[str, Any]]:
    """Per stage (recipe order): seeds, per-seed test scores — the selection score (``main``, SSC: mIoU) and
    the metric's next column (``second``, SSC: IoU) at the best-validation checkpoint, ``main`` at the last
    step (``last_main``) — their mean and sample std, and the per-seed differences in ``main`` to
    ``baseline`` with their mean and std."""
    seeds = sorted(results_by_seed)
    per_stage: dict[str, dict[int, dict[str, Any]]] = {}
    for seed in seeds:
        for result in results_by_seed[seed]:
            per_stage.setdefault(result.name, {})[seed] = stage_row(result.summary)
    base = per_stage.get(baseline or "", {})
    rows = []
    for name, by_seed in per_stage.items():
        got = sorted(by_seed)
        first = by_seed[got[0]]
        view: ScoreView = first["view"]
        nan = float("nan")
        pick = {"main": lambda r: r["best"][view.main[0]],
                "second": lambda r: r["best"][view.second[0]] if view.second else nan,
                "last_main": lambda r: r["last"][view.main[0]]}
        row: dict[str, Any] = {"stage": name, "label": first["label"], "seeds": got, "view": view,
                               "objectives": first["objectives"]}
        for key, get in pick.items():
            values = [get(by_seed[s]) for s in got]
            row[key] = values
            row[f"{key}_mean"], row[f"{key}_std"] = _mean_std(values)
        comparable = base and name != baseline and base[min(base)]["view"] == view
        paired = [pick["main"](by_seed[s]) - pick["main"](base[s]) for s in got if s in base] if comparable else []
        row["delta"] = paired
        row["delta_mean"], row["delta_std"] = _mean_std(paired) if paired else (math.nan, math.nan)
        rows.append(row)
    return rows


def _pm(mean: float, std: float, scale: float = 100.0, sign: str = "") -> str:
    value = f"{scale * mean:{sign}.2f}" if scale != 1.0 else f"{mean:{sign}.4g}"
    if math.isnan(std):
        return value
    return f"{value} ± {scale * std:.2f}" if scale != 1.0 else f"{value} ± {std:.2g}"


def _deltas(row: dict[str, Any]) -> tuple[str, str]:
    if not row["delta"]:
        return "—", "—"
    scale = row["view"].main[2]
    per_seed = " / ".join(f"{scale * d:+.2f}" if scale != 1.0 else f"{d:+.4g}" for d in row["delta"])
    return per_seed, _pm(row["delta_mean"], row["delta_std"], scale, "+")


def _view(rows: list[dict[str, Any]]) -> ScoreView | None:
    return rows[0]["view"] if rows else None


def _headers(view: ScoreView | None) -> list[str]:
    main = view.main[1] if view else "score"
    second = view.second[1] if view and view.second else "—"
    return [f"{main} best", f"{second} best", f"{main} last", f"Δ {main} per seed", f"Δ {main}"]


def _cells(row: dict[str, Any]) -> list[str]:
    view: ScoreView = row["view"]
    second = view.second[2] if view.second else 1.0
    return [_pm(row["main_mean"], row["main_std"], view.main[2]), _pm(row["second_mean"], row["second_std"], second),
            _pm(row["last_main_mean"], row["last_main_std"], view.main[2]), *_deltas(row)]


def seeds_table(rows: list[dict[str, Any]], baseline: str | None) -> Any:
    from rich.table import Table

    seeds = sorted({s for r in rows for s in r["seeds"]})
    table = Table(title=f"distilkit seeds {', '.join(map(str, seeds))} — test split, mean ± std over seeds, "
                        f"'best' = best-validation checkpoint; Δ = paired difference to '{baseline or '—'}'")
    for col in ("stage", "distillation", *_headers(_view(rows))):
        table.add_column(col, justify="left" if col in ("stage", "distillation") else "right")
    for row in rows:
        table.add_row(row["label"], row["objectives"], *_cells(row))
    return table


def write_seeds_report(root: Path, rows: list[dict[str, Any]], baseline: str | None, console: Any) -> Path:
    """Print the table and write ``seeds.md`` (and ``seeds.png``: each seed as a dot, the mean as a bar)."""
    console.print(seeds_table(rows, baseline))
    seeds = sorted({s for r in rows for s in r["seeds"]})
    view = _view(rows)
    main = view.main[1] if view else "score"
    title = view.title if view else "scores"
    lower = " (lower is better)" if view is not None and view.lower_is_better else ""
    cols = ["stage", "distillation", "seeds", *_headers(view)]
    lines = [f"# {root.name}: seeds {', '.join(map(str, seeds))}", "",
             f"Test split, {title}, mean ± sample std over the seeds; 'best' = the checkpoint with the best "
             f"validation {main}{lower}, 'last' = the final step. Δ = the paired difference in test {main} to "
             f"'{baseline or '—'}', seed by seed.", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for row in rows:
        lines.append(f"| {row['label']} | {row['objectives']} | {','.join(map(str, row['seeds']))} | "
                     + " | ".join(_cells(row)) + " |")
    lines += ["", f"![test {main} per seed](seeds.png)", ""]
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

    view = _view(rows)
    _, name, scale = view.main if view else ("", "score", 1.0)
    fig, ax = plt.subplots(figsize=(max(6.0, 0.6 * len(rows) + 2), 4.0))
    for i, row in enumerate(rows):
        ax.bar(i, scale * row["main_mean"], color="#9ecae1", yerr=None if math.isnan(row["main_std"]) else
               scale * row["main_std"], capsize=3)
        ax.scatter([i] * len(row["main"]), [scale * v for v in row["main"]], color="#08519c", s=12, zorder=3)
    ax.set_xticks(range(len(rows)), [r["label"] for r in rows], rotation=45, ha="right", fontsize=8)
    ax.set_ylabel(f"test {name}{' (%)' if scale == 100 else ''}, best-val checkpoint")
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
