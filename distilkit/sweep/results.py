"""A sweep's results: the finished runs' summaries as a table over seeds (mean ± std, paired differences to
the baseline with 95 % intervals), ``results.md``, ``results.csv`` (one line per run) and ``results.png``."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from distilkit.files import atomic_write_text
from distilkit.report.scores import stage_row
from distilkit.report.seeds import seed_rows, write_seeds_report


@dataclass
class RunRecord:
    """One finished run of a sweep: a variant (or an upstream stage) at a seed."""

    name: str  # the variant, or the upstream stage
    seed: int
    run_dir: Path
    summary: dict[str, Any]
    upstream: bool = False


def sweep_rows(records: list[RunRecord], baseline: str | None,
               order: list[str]) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows of :func:`~distilkit.report.seeds.seed_rows` in ``order`` (variants first, then upstream stages), and
    a note for each upstream stage scored by another metric than the variants (a query-proposal stage's IoU and
    precision): such a stage is left out of the table, whose columns name the variants' metric. An upstream stage
    is trained once and not compared: its row has no Δ to the baseline."""
    by_seed: dict[int, list[RunRecord]] = {}
    for r in records:
        by_seed.setdefault(r.seed, []).append(r)
    upstream = {r.name for r in records if r.upstream}
    # an upstream stage is its own reference: seed_rows compares it with nothing
    rows = {row["stage"]: row for row in seed_rows(by_seed, baseline, {name: name for name in upstream},
                                                   method_keys(records))}
    variant_view = next((rows[n]["view"] for n in order if n in rows and n not in upstream), None)
    out, notes = [], []
    for name in order:
        if name not in rows:
            continue
        row = rows[name]
        if name in upstream:
            if variant_view is not None and row["view"] != variant_view:
                notes.append(_own_metric_note(row))
                continue
            row["label"] = f"*{row['label']}* (upstream)"
        out.append(row)
    return out, notes


_NOT_THE_METHOD = ("recipe", "stage", "hash", "label", "seed", "versions", "distilkit")


def method_keys(records: list[RunRecord]) -> dict[str, str]:
    """Per variant, what makes it a method: its resolved stage (``recipe.resolved.yaml`` of its lowest seed) without
    its name, label, seed and hash and without the objectives' weights. Two variants with one key differ only in
    weights — the rows among which validation chooses one; variants that differ in anything else (a teacher's mode,
    an objective's parameter, a task loss) are methods of their own. A run without the file keeps the summary's
    grouping (input and objectives)."""
    import json

    import yaml

    keys: dict[str, str] = {}
    for r in sorted((r for r in records if not r.upstream), key=lambda r: r.seed):
        path = r.run_dir / "recipe.resolved.yaml"
        if r.name in keys or not path.is_file():
            continue
        try:
            stage = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError):
            continue
        if not isinstance(stage, dict):
            continue
        stage = {k: v for k, v in stage.items() if k not in _NOT_THE_METHOD}
        stage["distill"] = [{k: v for k, v in t.items() if k != "weight"} if isinstance(t, dict) else t
                            for t in stage.get("distill") or []]
        keys[r.name] = json.dumps(stage, sort_keys=True, default=str)
    return keys


def _own_metric_note(row: dict[str, Any]) -> str:
    """One line for an upstream stage with a metric of its own: its scores at the best-validation checkpoint."""
    view = row["view"]
    scores = ", ".join(f"{col[1]} {view.fmt(col, row[f'{key}_mean'])}"
                       for col, key in ((view.main, "main"), (view.second, "second")) if col is not None)
    seeds = ", ".join(map(str, row["seeds"]))
    return (f"Upstream *{row['label']}* (seed {seeds}) is scored by its own metric, not in the table: "
            f"{row['split']} {scores} (best validation {view.main[1]} {view.fmt(view.main, row['val_mean'])}).")


def results_csv(records: list[RunRecord]) -> str:
    """One line per run: the variant, seed, run folder and every score at the best and the last checkpoint."""
    rows = [(r, stage_row(r.summary)) for r in records]
    keys: list[str] = []
    for _, row in rows:
        keys += [k for k, _, _ in row["view"].columns if k not in keys]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["variant", "label", "role", "seed", "metric", "split", "selected_by", "best_step", "steps",
                     "train_seconds", "input_wait_seconds", "threads", *[f"best_{k}" for k in keys], *[f"last_{k}" for k in keys], "val_best",
                     "run_dir"])
    for r, row in rows:
        view = row["view"]

        def num(d: dict[str, float], k: str) -> str:
            v = d.get(k, math.nan)
            return "" if isinstance(v, float) and math.isnan(v) else f"{v:.6g}"

        writer.writerow([r.name, row["label"], "upstream" if r.upstream else "variant", r.seed, view.metric,
                         row["split"], f"val {view.select}", row["best_step"], row["steps"],
                         r.summary.get("train_seconds", ""), r.summary.get("input_wait_seconds", ""),
                         r.summary.get("threads", ""),
                         *[num(row["best"], k) for k in keys],
                         *[num(row["last"], k) for k in keys], num({"v": row["val"]}, "v"), str(r.run_dir)])
    return buf.getvalue()


def write_results(root: Path, name: str, records: list[RunRecord], baseline: str | None, order: list[str],
                  console: Any, missing: list[str], extra: list[str] | None = None) -> Path:
    """Print the table; write results.md, results.csv and results.png under ``root`` (``extra``: lines for
    results.md's notes, printed too)."""
    rows, own_metric = sweep_rows(records, baseline, order)
    atomic_write_text(root / "results.csv", results_csv(records))
    notes = [f"Runs not finished (not in the table): {'; '.join(missing)}." if missing else "", *own_metric,
             *(extra or []), "One line per run, with every score and its folder: results.csv."]
    path = write_seeds_report(root, rows, baseline, console, stem="results", title=f"sweep {name}",
                              first="variant", notes=[n for n in notes if n])
    for note in [*own_metric, *(extra or [])]:
        console.print(note, highlight=False, soft_wrap=True)
    return path


__all__ = ["RunRecord", "method_keys", "results_csv", "sweep_rows", "write_results"]
