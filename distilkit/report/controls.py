"""Each method against its control teachers (issue 59, item 3): the difference that the teacher's knowledge makes.

A control row is a stage whose teacher is a control (``teacher.control``, :mod:`distilkit.engine.train.controls`;
its summary's ``teacher_control``) and whose name is its method's with ``.<control>`` added (``dist_3.shuffled``:
what a sweep's ``controls`` line adds). A gain over the undistilled student that the control gives as well is the
extra loss term's regularisation, not the teacher's knowledge (Mason-Williams et al., arXiv 2510.12615, 2026).

For each method and control: the per-seed paired differences method − control in the table's score (the seeds
both ran), their mean ± std and 95 % Student-t interval, and the two-sided p of "Δ = 0" adjusted by Holm over the
comparisons of the methods at their validation-chosen weights. The control rows themselves are no methods: they
are left out of the table's family (its corrections and ranks) and shown as chosen where their method is.
"""

from __future__ import annotations

import math
from typing import Any

from distilkit.report import multiple
from distilkit.report.family import p_text
from distilkit.report.numbers import interval, mean_std, pm, signed


def annotate(rows: list[dict[str, Any]]) -> None:
    """Set ``control_of`` on each control row (and its method's ``chosen``), and on each method with control rows
    ``vs_control``: per control kind, ``seeds``, ``delta`` (method − control, per seed), ``mean``, ``std``, ``ci``,
    ``p`` and, for the chosen methods, ``p_holm``."""
    by_name = {r["stage"]: r for r in rows}
    compared = []
    for row in rows:
        kind = row.get("control")
        method = by_name.get(row["stage"][:-len(kind) - 1]) if kind and row["stage"].endswith(f".{kind}") else None
        if method is None or method.get("control"):
            continue
        row["control_of"], row["chosen"] = method["stage"], method.get("chosen", True)
        seeds = [s for s in method["seeds"] if s in row["seeds"]]
        delta = [method["main"][method["seeds"].index(s)] - row["main"][row["seeds"].index(s)] for s in seeds]
        mean, std = mean_std(delta)
        entry = {"kind": kind, "label": row["label"], "seeds": seeds, "delta": delta, "mean": mean, "std": std,
                 "ci": multiple.t_interval(delta), "p": multiple.paired_t_pvalue(delta)}
        method.setdefault("vs_control", {})[kind] = entry
        if method.get("chosen", True) and len(delta) >= 2:
            compared.append(entry)
    for entry, adjusted in zip(compared, multiple.holm([e["p"] for e in compared])):
        entry["p_holm"] = adjusted


def is_control(row: dict[str, Any]) -> bool:
    """Whether a row is a control teacher's (no method of the table's family)."""
    return bool(row.get("control"))


def markdown(rows: list[dict[str, Any]]) -> list[str]:
    """The section of the report with each method against its controls (empty without control rows)."""
    methods = [r for r in rows if r.get("vs_control")]
    if not methods:
        return []
    view = methods[0]["view"]
    scale = view.main[2]
    k = sum("p_holm" in e for r in methods for e in r["vs_control"].values())
    lines = ["", "## Against the control teachers", "",
             f"Each method minus the same method, objectives and weights against a control teacher, seed by seed, in "
             f"{view.main[1]}: `random` = the teacher's architecture with random weights, `shuffled` = the real "
             "teacher's outputs for another training sample (one random cycle through the split). What a method "
             "gains over the undistilled student and also gains against a control is the extra loss term's "
             "regularisation, not the teacher's knowledge (Mason-Williams et al., arXiv 2510.12615). 'p Holm': the "
             f"paired t test's p adjusted over the {k} comparisons of the methods at their chosen weights.", "",
             "| method | control | seeds | Δ per seed | Δ | Δ 95 % interval | p Holm |", "|---|---|---|---|---|---|---|"]
    for row in methods:
        for kind, e in row["vs_control"].items():
            mark = " ◆" if row.get("chosen") and row.get("alternatives", 1) > 1 else ""
            lines.append(f"| {row['label']}{mark} | {kind} | {','.join(map(str, e['seeds']))} | "
                         f"{' / '.join(signed(d, scale) for d in e['delta'])} | {pm(e['mean'], e['std'], scale, '+')} | "
                         f"{interval(*e['ci'], scale)} | {p_text(e.get('p_holm', math.nan))} |")
    return lines + [""]


__all__ = ["annotate", "is_control", "markdown"]
