"""How a finished stage's scores are read and shown: the columns its metric declares, the selection key.

Reports and seed tables are built from these rows, so a stage scored by any registered metric (SSC
mIoU, a point cloud's Chamfer distance, ...) is shown with its own scores, none special-cased.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from distilkit.registry import METRICS


@dataclass(frozen=True)
class ScoreView:
    """The metric's table: ``columns`` (key, header, scale), the key that selected ``best``, the title."""

    metric: str
    select: str
    title: str
    columns: tuple[tuple[str, str, float], ...]
    per_class: tuple[str, str, float] | None = None
    first_class: int = 0
    lower_is_better: bool = False

    @property
    def main(self) -> tuple[str, str, float]:
        """The selection score's column: the headline of every table."""
        return next((c for c in self.columns if c[0] == self.select), (self.select, self.select, 1.0))

    @property
    def second(self) -> tuple[str, str, float] | None:
        """The first other column (SSC: completion IoU beside mIoU), shown at both checkpoints."""
        return next((c for c in self.columns if c[0] != self.select), None)

    @property
    def others(self) -> list[tuple[str, str, float]]:
        return [c for c in self.columns if c not in (self.main, self.second)]

    @property
    def headline(self) -> list[tuple[str, str, float]]:
        return [self.main] + ([self.second] if self.second else [])

    @classmethod
    def of(cls, summary: dict[str, Any]) -> "ScoreView":
        """The view of a stage summary (summaries written before metrics were recorded: SSC by mIoU)."""
        spec = summary.get("metric") or {"name": "ssc", "key": "miou"}
        metric = _layout(spec["name"])
        if metric is None:  # a plugin metric that is not installed now: its keys as they are
            keys = tuple(k for k, v in (summary.get("test", {}).get("best") or {}).items() if isinstance(v, float))
            return cls(spec["name"], spec["key"], f"{spec['name']} scores", tuple((k, k, 1.0) for k in keys))
        per_class = metric["per_class"]
        return cls(spec["name"], spec["key"], metric["title"] or f"{spec['name']} scores",
                   tuple((str(k), str(h), float(x)) for k, h, x in metric["columns"]),
                   (str(per_class[0]), str(per_class[1]), float(per_class[2])) if per_class else None,
                   int(metric["first_class"]), spec["key"] in metric["lower_is_better"])

    def fmt(self, column: tuple[str, str, float], value: float) -> str:
        """A score as shown; a score the summary lacks (written before its metric reported it) as "—"."""
        if value != value:  # NaN
            return "—"
        return f"{column[2] * value:.2f}" if column[2] != 1.0 else f"{value:.4g}"


def _layout(name: str) -> dict[str, Any] | None:
    """Metric ``name``'s table layout: from the registry where this process has loaded it or registered the metric
    itself (a script's or a test's ``METRICS.add``), else from the catalogue, without importing the metrics; a name
    the catalogue lacks is looked up in the registry (None: not installed)."""
    from distilkit.catalogue import cached
    from distilkit.registry import plugins_loaded

    if METRICS.registered(name) is None and not plugins_loaded():
        layout = cached("metrics", metric_layouts).get(name)
        if layout is not None:
            return layout
    metric = METRICS.get(name) if name in METRICS else None
    return _layout_of(metric) if metric is not None else None


def _layout_of(m: Any) -> dict[str, Any]:
    return {"title": m.TITLE, "columns": [list(c) for c in m.columns()],
            "per_class": list(m.PER_CLASS) if m.PER_CLASS else None, "first_class": m.PER_CLASS_FROM,
            "lower_is_better": sorted(m.LOWER_IS_BETTER)}


def metric_layouts() -> dict[str, dict[str, Any]]:
    """Every registered metric's table layout (title, columns, per-class column, lower-is-better keys), by each of
    its names, as JSON data: kept in the catalogue (:mod:`distilkit.catalogue`), so a report does not import the
    metrics (and torch) to read a summary."""
    out: dict[str, dict[str, Any]] = {}
    for e in METRICS:
        layout = _layout_of(e.obj)
        for name in (e.name, *METRICS.aliases_of(e.name)):
            out[name] = layout
    return out


UNSCORED = "no split"  # a stage trained on everything (no validation or test split): scores are "—"


def _step(step: int | None) -> int | str:
    """A checkpoint's step as shown ("—" where no checkpoint was chosen)."""
    return "—" if step is None or step < 0 else step


def _frames(n: int | None) -> str:
    """The input column of summaries written before adapters described their input."""
    return f"{n} frame{'s' if n != 1 else ''}" if n else ""


def stage_row(summary: dict[str, Any]) -> dict[str, Any]:
    """One stage's figures: test-split scores at the best-validation and the last checkpoint."""
    view = ScoreView.of(summary)
    test = summary.get("test") or {}
    best = test.get("best") or summary.get("best", {}).get("scores") or summary.get("last") or {}
    last = test.get("last") or summary.get("last") or {}
    val = summary.get("best", {}).get("scores") or {}
    nan = float("nan")
    return {"stage": summary["stage"], "label": summary.get("label", summary["stage"]), "adapter": summary["adapter"],
            "input": summary.get("input", _frames(summary.get("frames"))),
            "teacher": summary.get("teacher") or "—", "control": summary.get("teacher_control"),
            "objectives": ", ".join(summary.get("objectives", [])) or "—", "view": view,
            "objective_list": list(summary.get("objectives", [])),
            "best": {k: best.get(k, nan) for k, _, _ in view.columns},
            "last": {k: last.get(k, nan) for k, _, _ in view.columns},
            "val": val.get(view.select, nan),
            "best_step": _step(test.get("best_step", summary.get("best", {}).get("step"))),
            "steps": summary.get("steps"), "class_scores": best.get(view.per_class[0], []) if view.per_class else [],
            "class_names": list((summary.get("classes") or {}).get("names", []))[view.first_class:]
            if view.per_class else [],
            "class_voxels": best.get("class_voxels", []),  # the split's ground-truth voxels of each class
            "split": summary.get("report_split", "val") or UNSCORED}


def header(view: ScoreView, split: str) -> str:
    if split == UNSCORED:
        return f"{UNSCORED}: the data has neither a validation nor a test split, so nothing was scored"
    main = view.main[1]
    return (f"{split} split, {view.title}: 'best' = the checkpoint with the best validation {main}"
            f"{' (lowest)' if view.lower_is_better else ''} (its step shown), 'last' = the final step")


__all__ = ["UNSCORED", "ScoreView", "header", "stage_row"]
