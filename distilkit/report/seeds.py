"""Stages over several training seeds: mean ± sample std and paired differences with a 95 % interval.

Each seed is its own run (its own stage folders); this module only reads their summaries. Scores are the
test split at the best-validation checkpoint (and at the last step). The paired difference of a stage to
the baseline stage is taken seed by seed (same scenes, same seed), which removes the part of the spread
the two share; its 95 % interval is Student's t over the seeds (mean ± t₀.₉₇₅,ₙ₋₁ · s / √n). A method
"helps" here only when that interval lies above zero. ``distilkit run --seed`` and ``distilkit sweep``
both report through :func:`write_seeds_report`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from distilkit.files import atomic_write_text
from distilkit.report import classes, controls, family, scenes
from distilkit.report.multiple import t_interval, t_quantile as _t_quantile
from distilkit.report.numbers import interval, mean_std, pm, signed
from distilkit.report.scores import ScoreView, stage_row


def default_baseline(resolved: Any) -> str | None:
    """The first stage without distillation that no other stage uses as its teacher (the plain student)."""
    teachers = {s.teacher_from for s in resolved.stages.values() if s.teacher_from}
    for name in resolved.order:
        if not resolved.stages[name].distill and name not in teachers:
            return name
    return None


def seed_rows(results_by_seed: dict[int, list[Any]], baseline: str | None,
              compare: dict[str, str] | None = None, methods: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Per stage (recipe order): seeds, per-seed test scores — the selection score (``main``, SSC: mIoU) and
    the metric's next column (``second``, SSC: IoU) at the best-validation checkpoint, ``main`` at the last
    step (``last_main``) — their mean and sample std, and the per-seed differences in ``main`` to its reference
    (``compare``'s stage for it, else ``baseline``; ``row["reference"]``) with their mean and std. ``methods``: a
    stage's method key where the caller knows more than the summary (a sweep: the whole resolved stage but the
    objectives' weights); rows with one key are one method's weights (:func:`choose_on_validation`)."""
    seeds = sorted(results_by_seed)
    per_stage: dict[str, dict[int, dict[str, Any]]] = {}
    for seed in seeds:
        for result in results_by_seed[seed]:
            per_stage.setdefault(result.name, {})[seed] = {**stage_row(result.summary),
                                                           "scenes": scenes.read(getattr(result, "run_dir", None))}
    compare = compare or {}
    rows = []
    for name, by_seed in per_stage.items():
        reference = compare.get(name, baseline)
        base = per_stage.get(reference or "", {})
        got = sorted(by_seed)
        first = by_seed[got[0]]
        view: ScoreView = first["view"]
        nan = float("nan")
        pick = {"main": lambda r: r["best"][view.main[0]],
                "second": lambda r: r["best"][view.second[0]] if view.second else nan,
                "last_main": lambda r: r["last"][view.main[0]],
                "val": lambda r: r["val"]}
        row: dict[str, Any] = {"stage": name, "label": first["label"], "seeds": got, "view": view,
                               "reference": reference if name != reference else None,
                               "objectives": first["objectives"], "split": first["split"],
                               "control": first["control"],  # a control teacher's row (report.controls)
                               # weights of one method: the same input and objectives (a stage without any is alone)
                               "group": _group(name, first, (methods or {}).get(name))}
        for key, get in pick.items():
            values = [get(by_seed[s]) for s in got]
            row[key] = values
            row[f"{key}_mean"], row[f"{key}_std"] = mean_std(values)
        comparable = base and name != reference and base[min(base)]["view"] == view
        paired = [pick["main"](by_seed[s]) - pick["main"](base[s]) for s in got if s in base] if comparable else []
        row["delta"] = paired
        row["delta_mean"], row["delta_std"] = mean_std(paired)
        row["delta_ci"] = t_interval(paired)
        row["class_iou"] = {s: by_seed[s]["class_scores"] for s in got if by_seed[s]["class_scores"]}
        row["class_names"], row["class_voxels"] = first["class_names"], first["class_voxels"]
        row["scene_counts"] = {s: by_seed[s]["scenes"] for s in got if by_seed[s]["scenes"] is not None}
        rows.append(row)
    choose_on_validation(rows)
    controls.annotate(rows)  # each method against its control teachers; their rows leave the family
    family.annotate(rows)  # Holm and simultaneous intervals over the methods at their chosen weights
    scenes.annotate(rows, baseline)  # an interval over seeds and test scenes, where the runs kept their counts
    return rows


def _group(name: str, first: dict[str, Any], method: Any) -> Any:
    """Weights of one method: the caller's method key, else the same input and objectives (a stage without any
    objective is alone)."""
    if not first["objective_list"] or first["control"]:  # a control row follows its method (report.controls)
        return ("stage", name)
    if method is not None:
        return ("method", method)
    return (first["input"], tuple(o.split("×")[0] for o in first["objective_list"]))


def choose_on_validation(rows: list[dict[str, Any]]) -> None:
    """Mark each row ``chosen``: within a group of rows that differ only in weights (one ``group`` key: see
    :func:`_group`), the one with the best mean validation score over the seeds; a row alone in its group is its own
    choice. The test split plays no part in the choice. ``alternatives`` counts the group's rows."""
    groups: dict[Any, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(row["group"], []).append(row)
    for members in groups.values():
        sign = -1.0 if members[0]["view"].lower_is_better else 1.0
        scored = [r for r in members if not math.isnan(r["val_mean"])]
        best = max(scored, key=lambda r: sign * r["val_mean"]) if scored else members[0]
        for r in members:
            r["chosen"], r["alternatives"] = r is best, len(members)


def detectable_effect(std: float, n: int, power: float = 0.8, level: float = 0.95) -> float:
    """The paired difference that a two-sided ``level`` t-interval over ``n`` seeds excludes 0 for with
    probability about ``power``, when the paired differences spread by ``std``:
    (t_{(1+level)/2, n-1} + t_{power, n-1}) · std / √n (the usual normal-theory approximation)."""
    if n < 2 or math.isnan(std):
        return math.nan
    return (_t_quantile(0.5 + level / 2, n - 1) + _t_quantile(power, n - 1)) * std / math.sqrt(n)


def _deltas(row: dict[str, Any], corrected: bool = False) -> tuple[str, ...]:
    """Per seed, mean ± std, the interval (and, in a table with a family, Holm's p and the simultaneous interval)."""
    if not row["delta"]:
        return ("—",) * (5 if corrected else 3)
    scale = row["view"].main[2]
    per_seed = " / ".join(signed(d, scale) for d in row["delta"])
    out = (per_seed, pm(row["delta_mean"], row["delta_std"], scale, "+"), interval(*row["delta_ci"], scale))
    if corrected:
        out += (family.p_cell(row), interval(*row["sim_ci"], scale) if "sim_ci" in row else "—")
    return out


def _view(rows: list[dict[str, Any]]) -> ScoreView | None:
    return rows[0]["view"] if rows else None


def _per_row(rows: list[dict[str, Any]], baseline: str | None) -> bool:
    """Whether the rows take their differences to different stages (``report.compare``): then a column names each."""
    return any(r.get("reference") not in (None, baseline) for r in rows)


def _headers(view: ScoreView | None, split: str = "test", per_row: bool = False, corrected: bool = False) -> list[str]:
    main = view.main[1] if view else "score"
    second = view.second[1] if view and view.second else "—"
    return [f"val {main} (selects)", f"{split} {main} best", f"{split} {second} best", f"{split} {main} last",
            *(["Δ to"] if per_row else []), f"Δ {split} {main} per seed", f"Δ {split} {main}", "Δ 95 % interval",
            *(["p Holm", "simultaneous 95 %"] if corrected else [])]


def _cells(row: dict[str, Any], per_row: bool = False, corrected: bool = False) -> list[str]:
    view: ScoreView = row["view"]
    second = view.second[2] if view.second else 1.0
    ref = [row.get("reference") or "—"] if per_row else []
    return [pm(row["val_mean"], row["val_std"], view.main[2]), pm(row["main_mean"], row["main_std"], view.main[2]),
            pm(row["second_mean"], row["second_std"], second),
            pm(row["last_main_mean"], row["last_main_std"], view.main[2]), *ref, *_deltas(row, corrected)]


def _mark(row: dict[str, Any]) -> str:
    """The row's label, with ``◆`` where it is one of several weights of a method and the validation chose it."""
    return f"{row['label']} ◆" if row.get("chosen") and row.get("alternatives", 1) > 1 else row["label"]


def _weighs(rows: list[dict[str, Any]]) -> bool:
    """Whether some method was tried at several weights (then a table of the chosen ones leads)."""
    return any(r.get("alternatives", 1) > 1 for r in rows)


def _split(rows: list[dict[str, Any]]) -> str:
    return rows[0]["split"] if rows else "test"


def _rule(rows: list[dict[str, Any]]) -> str:
    """The selection rule: which checkpoint 'best' is."""
    view = _view(rows)
    if view is None:
        return "'best' = the best-validation checkpoint"
    return (f"'best' = the checkpoint with the best validation {view.main[1]}"
            f"{' (lowest)' if view.lower_is_better else ''}")


def seeds_table(rows: list[dict[str, Any]], baseline: str | None, what: str = "distilkit seeds",
                first: str = "stage") -> Any:
    from rich.table import Table

    seeds = sorted({s for r in rows for s in r["seeds"]})
    per_row, info = _per_row(rows, baseline), family.of(rows)
    to = "the stage in 'Δ to'" if per_row else f"'{baseline or '—'}'"
    corrected = (f"; over the family of {info['k']} methods at their chosen weights: Holm-adjusted p and "
                 f"simultaneous 95 % intervals ({info['method']})" if info else "")
    table = Table(title=f"{what} {', '.join(map(str, seeds))} — {_split(rows)} split, mean ± std over seeds, "
                        f"{_rule(rows)}; Δ = paired difference to {to} with its 95 % t-interval{corrected}")
    headers = _headers(_view(rows), _split(rows), per_row, info is not None)
    keep = [i for i, h in enumerate(headers) if "per seed" not in h]  # per seed: in the Markdown and the CSV
    for col in (first, "distillation", *[headers[i] for i in keep]):
        table.add_column(col, justify="left" if col in (first, "distillation") else "right")
    for row in rows:
        cells = _cells(row, per_row, info is not None)
        table.add_row(_mark(row), row["objectives"], *[cells[i] for i in keep])
    if _weighs(rows):
        table.caption = "◆ = of a method's weights, the one with the best mean validation score (the test split chose nothing)"
    return table


def power_note(rows: list[dict[str, Any]]) -> str:
    """What the table can resolve: the smallest paired difference its intervals detect 80 % of the time, from the
    seeds it has and the median spread of its paired differences."""
    n = max((len(r["delta"]) for r in rows), default=0)  # the compared rows (a shared teacher has one seed)
    stds = sorted(r["delta_std"] for r in rows if len(r["delta"]) == n and not math.isnan(r["delta_std"]))
    if n < 2 or not stds:
        return ""
    view = _view(rows)
    assert view is not None
    std = stds[len(stds) // 2]
    effect = detectable_effect(std, n)
    unit = view.main[2]
    fmt = (lambda v: f"{unit * v:.2f}") if unit != 1.0 else (lambda v: f"{v:.3g}")
    return (f"Power: with {n} seeds and a median spread of the paired differences of {fmt(std)} {view.main[1]}, a "
            f"true difference of about ±{fmt(effect)} {view.main[1]} gives an interval that excludes 0 in 80 % of "
            "repetitions; smaller effects can go unseen, and an interval that contains 0 is not evidence of no effect.")


def _md_rows(rows: list[dict[str, Any]], per_row: bool = False, corrected: bool = False) -> list[str]:
    return [f"| {_mark(row)} | {row['objectives']} | {','.join(map(str, row['seeds']))} | "
            + " | ".join(_cells(row, per_row, corrected)) + " |" for row in rows]


def seeds_markdown(rows: list[dict[str, Any]], baseline: str | None, title: str, first: str = "stage",
                   image: str | None = None, notes: list[str] | None = None, forest: str | None = None,
                   ranked: tuple[dict[str, Any] | None, str | None] = (None, None)) -> str:
    """The table as Markdown, with a paragraph that says what every number is. Where a method was tried at
    several weights, a first table shows each method at the weight the validation split chose."""
    seeds = sorted({s for r in rows for s in r["seeds"]})
    view = _view(rows)
    main = view.main[1] if view else "score"
    split = _split(rows)
    per_row, corrected = _per_row(rows, baseline), family.of(rows) is not None
    to = "the stage in 'Δ to' (the recipe's report.compare)" if per_row else f"'{baseline or '—'}'"
    cols = [first, "distillation", "seeds", *_headers(view, split, per_row, corrected)]
    head = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    power, described = power_note(rows), family.describe(rows)
    lines = [f"# {title}", "",
             f"{split.capitalize()} split, {view.title if view else 'scores'}, mean ± sample std over seeds "
             f"{', '.join(map(str, seeds))}; {_rule(rows)}, 'last' = the final step; 'val' = the validation score of "
             f"that checkpoint, the only score used to choose anything. Δ = the paired difference in {split} {main} to "
             f"{to}, seed by seed, with its 95 % Student-t interval over the seeds (an interval that "
             "contains 0: no measurable effect).", *(["", described] if described else []),
             *(["", power] if power else []),
             *(["", *notes] if notes else []), ""]
    if _weighs(rows):
        chosen = [r for r in rows if r.get("chosen")]
        lines += ["## Each method at the weight chosen on validation", "",
                  f"Of a method's weights, the one with the best mean validation {main} over the seeds (◆ below); "
                  f"its {split} scores are reported as they are.", "", *head, *_md_rows(chosen, per_row, corrected)]
        if forest and corrected:
            lines += ["", f"![each method at its chosen weight: the per-method and the simultaneous 95 % intervals]"
                          f"({forest.replace('_forest.png', '_family.png')})"]
        lines += ["", "## Every variant", "", *head, *_md_rows(rows, per_row, corrected)]
    else:
        lines += [*head, *_md_rows(rows, per_row, corrected)]
    if forest:
        lines += ["", f"![paired differences to {to} with 95 % intervals]({forest})"]
    if image:
        lines += ["", f"![{split} {main} per seed]({image})"]
    if ranked[0] is not None:
        lines += ["", *family.ranks_markdown(*ranked)]
    lines += controls.markdown(rows) + scenes.markdown(rows)
    return "\n".join(lines + [""])


def write_seeds_report(root: Path, rows: list[dict[str, Any]], baseline: str | None, console: Any,
                       stem: str = "seeds", title: str | None = None, first: str = "stage",
                       notes: list[str] | None = None) -> Path:
    """Print the table and write ``<stem>.md``, ``<stem>.png`` (each seed as a dot, the mean as a bar with its std
    as an error bar), ``<stem>_forest.png`` (each row's paired difference to the baseline with its 95 %
    interval, a line at 0), where the methods are a family chosen among weights ``<stem>_family.png`` (each method at
    its chosen weight, with its simultaneous interval) and ``<stem>_cd.png`` (their ranks:
    :mod:`~distilkit.report.family`), and where the runs have per-class scores ``<stem>_classes.md`` and ``.png``
    (:mod:`~distilkit.report.classes`)."""
    seeds = sorted({s for r in rows for s in r["seeds"]})
    console.print(seeds_table(rows, baseline, "distilkit seeds" if stem == "seeds" else f"{root.name}: seeds", first))
    power = power_note(rows)
    if power:
        console.print(power)
    forest = f"{stem}_forest.png" if any(r["delta"] for r in rows) else None
    ranked = family.ranks(rows, baseline)
    title = title or f"{root.name}: seeds {', '.join(map(str, seeds))}"
    per_class = classes.write_classes(root, stem, rows, baseline, title, console)
    if per_class is not None:
        notes = [*(notes or []), f"Where each method helps, class by class: [{per_class.name}]({per_class.name})."]
    path = root / f"{stem}.md"
    atomic_write_text(path, seeds_markdown(rows, baseline, title, first, f"{stem}.png", notes, forest,
                                           (ranked, f"{stem}_cd.png")))
    try:
        _plot(root / f"{stem}.png", rows)
        if forest:
            _forest(root / forest, rows, baseline)
            if _weighs(rows) and family.of(rows) is not None:
                _forest(root / forest.replace("_forest.png", "_family.png"), rows, baseline, chosen_only=True)
        family.plot(root / f"{stem}_cd.png", ranked)
    except Exception as exc:  # a plotting problem must not lose the table
        console.print(f"[yellow]{stem} plots not written: {exc}[/]")
    console.print(f"{'seeds' if stem == 'seeds' else stem} report: {path}")
    return path


def _plot(path: Path, rows: list[dict[str, Any]]) -> None:
    from distilkit.report import plots

    view = _view(rows)
    _, name, scale = view.main if view else ("", "score", 1.0)
    fig, (ax,) = plots.figure(1, width=max(6.0, 0.6 * len(rows) + 2))
    for i, row in enumerate(rows):
        ax.bar(i, scale * row["main_mean"], color="#9ecae1", yerr=None if math.isnan(row["main_std"]) else
               scale * row["main_std"], capsize=3)
        ax.scatter([i] * len(row["main"]), [scale * v for v in row["main"]], color="#08519c", s=12, zorder=3)
    ax.set_xticks(range(len(rows)), [plots.short(_mark(r).replace("*", ""), 60) for r in rows], rotation=45, ha="right",
                  fontsize=8)
    ax.set_ylabel(f"{_split(rows)} {name}{' (%)' if scale == 100 else ''}, best-val checkpoint")
    ax.set_title("mean ± std over seeds; dots: single seeds")
    plots.save(fig, path)


def _forest(path: Path, rows: list[dict[str, Any]], baseline: str | None, chosen_only: bool = False) -> None:
    """The question a comparison asks, as a picture: per row, the paired difference to the baseline (mean, dot)
    with its 95 % interval (bar) and the single seeds (small marks), a line at 0; rows chosen on validation
    in dark blue, the other weights in grey. ``chosen_only``: the table's family alone (each method at its chosen
    weight, no control row), best first, each with its simultaneous interval as a thin line beside the bar — the
    figure of a paper's claims, whose scale the control teachers' collapses do not stretch."""
    from distilkit.report import plots

    shown = [r for r in rows if r["delta"]]
    if chosen_only:
        shown = sorted(family.family(rows), key=lambda r: -r["delta_mean"])
    view = _view(shown)
    _, name, scale = view.main if view else ("", "score", 1.0)
    fig, (ax,) = plots.figure(1, width=7.0, height=max(2.5, 0.38 * len(shown) + 1.2))
    for i, row in enumerate(reversed(shown)):
        colour = "#08306b" if row.get("chosen", True) else "#969696"
        low, high = row["delta_ci"]
        if not math.isnan(low):
            ax.plot([scale * low, scale * high], [i, i], color=colour, linewidth=2.2, solid_capstyle="butt")
        if chosen_only and row.get("sim_ci"):
            ax.plot([scale * v for v in row["sim_ci"]], [i - 0.18] * 2, color=colour, linewidth=0.9)
        ax.scatter([scale * d for d in row["delta"]], [i + 0.2] * len(row["delta"]), facecolors="none",
                   edgecolors=colour, s=14, alpha=0.7, linewidths=0.8, zorder=2)
        ax.scatter([scale * row["delta_mean"]], [i], color=colour, s=30, zorder=3)
    ax.axvline(0.0, color="#cb181d", linewidth=1.0)
    per_row = _per_row(rows, baseline)
    ticks = [plots.short(_mark(r).replace("*", ""), 60) + (f" − {r['reference']}" if per_row else "")
             for r in reversed(shown)]
    ax.set_yticks(range(len(shown)), ticks, fontsize=8)
    unit = " (points)" if scale == 100 else ""
    to = "its reference stage" if per_row else f"'{baseline or '—'}'"
    ax.set_xlabel(f"Δ {_split(rows)} {name}{unit} to {to}, paired by seed")
    if chosen_only:
        info = family.of(rows) or {}
        ax.set_title(f"each method at its chosen weight: 95 % t-interval (thick),\nsimultaneous 95 % over the "
                     f"{info.get('k', len(shown))} methods ({info.get('method', '')}, thin); circles: single seeds",
                     fontsize=9)
    else:
        ax.set_title("mean and 95 % t-interval of the paired differences; circles: single seeds", fontsize=9)
    plots.save(fig, path)
