"""A recipe's report: the comparison table of its stages (rich), ``report.md`` and ``report.png`` beside the
stage folders."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from distilkit.files import atomic_write_text
from distilkit.report.scores import ScoreView, header, stage_row


def _groups(rows: list[dict[str, Any]]) -> list[tuple[ScoreView, list[int]]]:
    """Rows by the view of their scores (one group unless stages are scored by different metrics or keys)."""
    out: dict[ScoreView, list[int]] = {}
    for i, row in enumerate(rows):
        out.setdefault(row["view"], []).append(i)
    return list(out.items())


def _score_columns(view: ScoreView) -> list[str]:
    head = [c[1] for c in view.headline]
    return ([f"{h} best" for h in head] + [c[1] for c in view.others] + ["best step"] + [f"{h} last" for h in head]
            + [f"val {view.main[1]}"])


def _score_cells(row: dict[str, Any], view: ScoreView, rich: bool = False) -> list[str]:
    head = view.headline
    cells = [view.fmt(c, row["best"][c[0]]) for c in head]
    cells += [] if rich else [view.fmt(c, row["best"][c[0]]) for c in view.others]
    return cells + [str(row["best_step"])] + [view.fmt(c, row["last"][c[0]]) for c in head] + [
        view.fmt(view.main, row["val"])]


WIDE = 150  # a console at least this wide gets a column for every field; a narrower one, the compact layout


class ResultsTable:
    """The stages' comparison table, laid out for the console it is printed on: a column per field where it is
    wide enough, else one column that gathers each stage's label, model, input, teacher and distillation (folded
    as needed) beside short score headers. Scores and the status are never cut, at any width."""

    def __init__(self, results: list[Any], note: str | None = None) -> None:
        self.results, self.note = results, note

    def __rich_console__(self, console: Any, options: Any) -> Any:
        rows = [stage_row(r.summary) for r in self.results]
        wide = options.max_width >= WIDE
        for view, members in _groups(rows):
            yield self._table(rows, members, view, wide)
        if self.note:
            yield self.note

    def _table(self, rows: list[dict[str, Any]], members: list[int], view: ScoreView, wide: bool) -> Any:
        from rich.table import Table

        table = Table(title=f"distilkit results — {header(view, rows[members[0]]['split'])}")
        scores = [c for c in _score_columns(view) if c not in [o[1] for o in view.others]]
        text = ("stage", "model", "input", "teacher", "distillation") if wide else ("stage",)
        for col in text:
            table.add_column(col, overflow="fold", ratio=1)
        cells = [[*_score_cells(rows[i], view, rich=True), "reused" if self.results[i].reused else "trained"]
                 for i in members]
        for j, col in enumerate([*scores, "status"]):
            width = max(len(c[j]) for c in cells)
            heading = col if wide else col.replace(" ", "\n")  # short headings wrap at their spaces, never the values
            table.add_column(heading, justify="left" if col == "status" else "right", no_wrap=True,
                             min_width=max(width, min(len(w) for w in heading.split("\n"))))
        for i, score_cells in zip(members, cells):
            row = rows[i]
            if wide:
                label = [row["label"], row["adapter"], row["input"], row["teacher"], row["objectives"]]
            else:
                detail = ", ".join(p for p in (row["adapter"], row["input"]) if p and p != "—")
                teacher = f" ← {row['teacher']}" if row["teacher"] not in ("", "—") else ""
                objectives = f"\n{row['objectives']}" if row["objectives"] not in ("", "—") else ""
                label = [f"{row['label']}\n[dim]{detail}{teacher}{objectives}[/]"]
            table.add_row(*label, *score_cells)
        return table


def results_table(results: list[Any], note: str | None = None) -> Any:
    """The comparison table of the stages (a rich renderable that fits its console's width; ``note``: a line
    printed under it)."""
    return ResultsTable(results, note)


def class_rows(rows: list[dict[str, Any]], members: list[int], view: ScoreView,
               class_names: tuple[str, ...]) -> tuple[list[str], list[list[str]]]:
    """The papers' layout of one metric's stages: header and rows of the stage, every score column but the selection
    key's runners-up, then each class's score (best checkpoint)."""
    assert view.per_class is not None
    scores = [c for c in view.columns if c[0] not in ("precision", "recall")]
    names = class_names[view.first_class:]
    head = ["stage", *(c[1] for c in scores), *names]
    out = []
    for i in members:
        row = rows[i]
        classes = row["class_scores"]
        out.append([row["label"], *(view.fmt(c, row["best"][c[0]]) for c in scores),
                    *(f"{view.per_class[2] * classes[c]:.1f}" if len(classes) > c else "—" for c in range(len(names)))])
    return head, out


def class_tables(results: list[Any], class_names: tuple[str, ...]) -> tuple[Any, list[str]]:
    """The per-class tables (``report: {per_class: true}``) as a rich renderable (a column per stage) and as
    Markdown lines (the papers' layout: a row per stage)."""
    from rich.console import Group
    from rich.table import Table

    rows = [stage_row(r.summary) for r in results]
    tables, lines = [], []
    for view, members in _groups(rows):
        if view.per_class is None:
            continue
        head, body = class_rows(rows, members, view, class_names)
        title = f"{rows[members[0]]['split']} split, {view.per_class[1]} per class (best checkpoint), {view.title}"
        table = Table(title=title)  # the console's: one column per stage (the papers' rows would not fit its width)
        table.add_column("score / class")
        for cells in body:
            table.add_column(cells[0], justify="right")
        for j, name in enumerate(head[1:], 1):
            table.add_row(name, *(cells[j] for cells in body))
        tables.append(table)
        lines += [f"## {title[0].upper()}{title[1:]}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(cells) + " |" for cells in body] + [""]
    return Group(*tables), lines


def _seeds(default: int, results: list[Any]) -> str:
    """'Seed 0', or each stage's seed when stages have their own."""
    seeds = {r.name: r.summary.get("seed", default) for r in results}
    if len(set(seeds.values())) <= 1:
        return f"Seed {next(iter(seeds.values()), default)}"
    return "Seeds " + ", ".join(f"{n} {s}" for n, s in seeds.items())


def write_report(pipeline: Any, results: list[Any]) -> Path:
    """Print the comparison table and write ``report.md`` and ``report.png`` beside the stage folders."""
    note = pipeline.recipe.report.note
    pipeline.console.print(results_table(results, note))
    root: Path = pipeline.root
    rows = [stage_row(r.summary) for r in results]
    groups = _groups(rows)
    lines = [f"# {pipeline.recipe.name}", ""]
    for view, members in groups:
        cols = ["stage", "model", "input", "teacher", "distillation", *_score_columns(view), "run"]
        lines += [f"{_seeds(pipeline.recipe.seed, [results[i] for i in members])}; {header(view, rows[members[0]]['split'])}.", "",
                  "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
        for i in members:
            row = rows[i]
            cells = [row["label"], row["adapter"], row["input"], row["teacher"], row["objectives"],
                     *_score_cells(row, view), "reused" if results[i].reused else "trained"]
            lines.append("| " + " | ".join(cells) + " |")
        lines.append("")
        if view.per_class is not None:
            key, name, scale = view.per_class
            lines += [f"## Per-class {name} ({'%, ' if scale == 100 else ''}best checkpoint)", "",
                      "| class | " + " | ".join(rows[i]["label"] for i in members) + " |", "|---|" + "---|" * len(members)]
            for c, cname in enumerate(pipeline.resolved.data_info.class_names[view.first_class:]):
                vals = [f"{scale * rows[i]['class_scores'][c]:.1f}" if len(rows[i]["class_scores"]) > c else "—"
                        for i in members]
                lines.append(f"| {cname} | " + " | ".join(vals) + " |")
            lines.append("")
    if note:
        lines += [note, ""]
    if pipeline.recipe.report.per_class:
        renderable, class_lines = class_tables(results, pipeline.resolved.data_info.class_names)
        pipeline.console.print(renderable)
        lines += class_lines
    lines += [f"![training loss and validation {groups[0][0].main[1] if groups else 'score'}](report.png)", ""]
    try:
        atomic_write_text(root / "report.md", "\n".join(lines))
    except PermissionError:  # a finished run in a read-only folder: the table above is its report
        pipeline.console.print(f"[yellow]{root}: read-only, report.md not written (the table above is the report)[/]")
        return root / "report.md"
    try:
        _plot(root / "report.png", results, rows)
    except Exception as exc:  # a plotting problem must not lose a finished run
        pipeline.console.print(f"[yellow]report.png not written: {exc}[/]")
    pipeline.console.print(f"report: {root / 'report.md'}")
    return root / "report.md"


def _plot(path: Path, results: list[Any], rows: list[dict[str, Any]]) -> None:
    from distilkit.report import plots

    fig, (ax1, ax2) = plots.figure(2, width=5.5)
    positive = False
    for r in results:
        task = plots.task_loss(plots.read_log(r.run_dir)[0])
        if task:
            ax1.plot(*task["task loss"], label=plots.short(r.summary.get("label", r.name)))
            positive = positive or any(v > 0 for v in task["task loss"][1])
    ax1.set_xlabel("step")
    ax1.set_ylabel("task loss (without distillation terms)")
    if positive:  # a log axis needs a positive value (a batch of unlabelled scans has a task loss of 0)
        ax1.set_yscale("log")
    ax1.legend(fontsize=8)
    ax1.set_title("training loss")
    view, members = _groups(rows)[0] if rows else (None, [])
    if view is not None:  # the first metric's stages (all of them, unless stages use different metrics)
        labels = [plots.short(rows[i]["label"]) for i in members]
        (key, name, scale), second = view.main, view.second
        ax2.bar(labels, [scale * rows[i]["best"][key] for i in members], color="tab:blue", label=name)
        if second is not None:
            ax2.plot(labels, [second[2] * rows[i]["best"][second[0]] for i in members], "o", color="tab:orange",
                     label=second[1])
        ax2.set_ylabel("%" if scale == 100 else name)
    ax2.set_title(f"{rows[0]['split'] if rows else 'test'} split, best-validation checkpoint")
    ax2.legend(fontsize=8)
    ax2.tick_params(axis="x", rotation=20)
    plots.save(fig, path)
