"""A comparison table's methods as one family (issue 59): corrections for claiming several at once, and ranks.

The family is the table's methods, each at the weight the validation split chose (a method tried at one weight is
its own choice), compared with the baseline by paired differences over the seeds (:func:`family`). For it:

- each method's two-sided p-value of "Δ = 0" (the paired t test whose interval the table gives) adjusted by Holm's
  step-down over the family (:func:`~distilkit.report.multiple.holm`), which controls the chance of any false claim
  at 5 %, where ten unadjusted intervals would make one by luck about 40 % of the time;
- intervals that hold for every method of the family at once (:func:`~distilkit.report.multiple.simultaneous_intervals`:
  max-t, the studentised maximum under the seeds' correlation between methods, by Monte Carlo; Bonferroni where the
  methods do not share their seeds);
- Friedman's rank test over seeds × (baseline and methods), Iman–Davenport's F, the average ranks and Nemenyi's
  critical difference, drawn as a critical-difference diagram (Demšar 2006, JMLR 7:1–30).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from distilkit.report import multiple

LEVEL = 0.95


def family(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows a table's claims are about: those with paired differences to the baseline (two seeds at least),
    each method at the weight chosen on validation; a control teacher's row is no method (:mod:`.controls`)."""
    return [r for r in rows if len(r["delta"]) >= 2 and r.get("chosen", True) and not r.get("control")]


def annotate(rows: list[dict[str, Any]]) -> None:
    """Set ``p``, ``p_holm``, ``sim_ci`` and ``family`` (its size ``k``, seeds ``n`` and simultaneous method) on each
    row of the :func:`family`, where it has two methods at least; the other rows get none of them."""
    fam = family(rows)
    for row in rows:
        for key in ("p", "p_holm", "sim_ci", "family"):
            row.pop(key, None)
    if len(fam) < 2:
        return
    pvalues = [multiple.paired_t_pvalue(r["delta"]) for r in fam]
    shared = len({tuple(r["seeds"]) for r in fam}) == 1 and len({len(r["delta"]) for r in fam}) == 1
    method = "max-t" if shared else "bonferroni"
    intervals = multiple.simultaneous_intervals({r["stage"]: r["delta"] for r in fam}, LEVEL, method=method)
    info = {"k": len(fam), "n": max(len(r["delta"]) for r in fam), "method": method}
    for row, p, adjusted in zip(fam, pvalues, multiple.holm(pvalues)):
        row["p"], row["p_holm"], row["sim_ci"], row["family"] = p, adjusted, intervals[row["stage"]], info


def of(rows: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The family's size, seeds and simultaneous method as :func:`annotate` left them (None: no family)."""
    return next((r["family"] for r in rows if "family" in r), None)


def describe(rows: list[dict[str, Any]]) -> str:
    """The sentence that names the family and the corrections (empty without a family)."""
    info = of(rows)
    if info is None:
        return ""
    how = ("max-t: the studentised maximum over the methods, its critical value by Monte Carlo under the seeds' "
           "sample correlation between methods" if info["method"] == "max-t" else
           "Bonferroni: each at level 1 − 0.05/k, the methods not sharing their seeds")
    return (f"Family: the {info['k']} methods compared with the baseline, each at its validation-chosen weight. "
            f"'p Holm' = the p-value of Δ = 0 (the paired t test) adjusted by Holm's step-down over the "
            f"{info['k']} (a method whose paired differences are all equal has no p-value, shown as —, and is left "
            "out of the adjustment): a claim with p Holm < 0.05 keeps the chance of any false claim in the table "
            "under 5 %. "
            f"'simultaneous 95 %' = intervals that hold for all {info['k']} at once ({how}); they are wider than "
            "the per-method intervals, which hold each on its own.")


def ranks(rows: list[dict[str, Any]], baseline: str | None) -> dict[str, Any] | None:
    """Friedman's test over the seeds every compared row shares (the baseline and the :func:`family`), the average
    ranks (1 = best; the metric's direction), Iman–Davenport's F, Nemenyi's critical difference at 0.05 and its
    groups (None: fewer than three rows or two seeds)."""
    base = next((r for r in rows if r["stage"] == baseline), None)
    members = ([base] if base is not None else []) + family(rows)
    if len(members) < 3:
        return None
    seeds = sorted(set.intersection(*(set(r["seeds"]) for r in members)))
    if len(seeds) < 2:
        return None
    import numpy as np

    sign = -1.0 if members[0]["view"].lower_is_better else 1.0
    scores = np.array([[sign * r["main"][r["seeds"].index(s)] for r in members] for s in seeds])
    if np.isnan(scores).any():
        return None
    result = multiple.friedman(scores)
    labels = [r["label"] for r in members]
    average = dict(zip(labels, (float(x) for x in result.ranks)))
    cd = multiple.nemenyi_cd(len(members), len(seeds))
    return {"ranks": average, "cd": cd, "groups": multiple.cd_groups(average, cd), "result": result,
            "seeds": seeds}


def ranks_markdown(info: dict[str, Any] | None, image: str | None) -> list[str]:
    """The section of ``results.md`` with the ranks (empty without them)."""
    if info is None:
        return []
    r, cd = info["result"], info["cd"]
    order = sorted(info["ranks"].items(), key=lambda kv: kv[1])
    lines = ["## All methods at once, by rank", "",
             f"Friedman's test over seeds {', '.join(map(str, info['seeds']))} × the {r.k} rows (the baseline and "
             f"each method at its chosen weight; rank 1 = best on the seed): χ²_F = {r.chi2:.2f} (p "
             f"{_is(r.p_chi2)}), Iman–Davenport F = {r.f:.2f} (p {_is(r.p_f)}). Nemenyi's critical difference at "
             f"0.05: CD = {cd:.2f}; two rows whose average ranks differ by less are not told apart "
             "(Demšar 2006). With few seeds the CD is wide: the ranks order the methods, they seldom separate them.",
             "", "| row | average rank |", "|---|---|", *[f"| {name} | {rank:.2f} |" for name, rank in order], ""]
    if info["groups"]:
        lines += ["Not told apart (average ranks within CD): "
                  + "; ".join("{" + ", ".join(g) + "}" for g in info["groups"]) + ".", ""]
    if image:
        lines += [f"![critical-difference diagram: average ranks, rows joined by a bar are within CD]({image})", ""]
    return lines


def p_text(p: float) -> str:
    """A p-value as the reports write it."""
    return "—" if math.isnan(p) else f"{p:.2g}" if p >= 1e-4 else "< 1e-4"


def _is(p: float) -> str:
    text = p_text(p)
    return text if text.startswith("<") else f"= {text}"


def p_cell(row: dict[str, Any]) -> str:
    """A row's Holm-adjusted p-value as the table shows it (— outside the family)."""
    return p_text(row["p_holm"]) if "p_holm" in row else "—"


def plot(path: Path, info: dict[str, Any] | None) -> bool:
    """The critical-difference diagram (nothing without ranks); whether it was drawn."""
    if info is None:
        return False
    multiple.plot_cd(info["ranks"], info["cd"], path, title=f"average ranks over {len(info['seeds'])} seeds; "
                                                            f"CD = {info['cd']:.2f} (Nemenyi, 0.05)")
    return True


__all__ = ["LEVEL", "annotate", "describe", "family", "of", "p_cell", "p_text", "plot", "ranks", "ranks_markdown"]
