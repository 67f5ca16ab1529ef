"""A comparison table's methods as one family (issue 59, items 1 and 2): the table's Holm-adjusted p-values against
statsmodels on scipy's paired t tests, its simultaneous intervals between the per-method and the Bonferroni ones,
Friedman's ranks against scipy, and the report's columns, sentence, ranks section and diagram."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console
from scipy import stats
from statsmodels.stats.multitest import multipletests

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from distilkit.report import family
from distilkit.report.seeds import seed_rows, write_seeds_report
from test_seeds import fake

SEEDS = (0, 1, 2, 3, 4, 5)


def _results(rng: np.random.Generator, lower: bool = False) -> tuple[dict, dict]:
    """Six seeds of a baseline and five methods, one of them at two weights (the validation prefers ×4)."""
    effects = {"none": 0.0, "kd_1": 0.0, "kd_4": 0.01, "dist": 0.02, "nst": -0.01, "pkt": 0.0, "fit": 0.005}
    objectives = {"none": (), "kd_1": ("kd×1",), "kd_4": ("kd×4",), "dist": ("dist×1",), "nst": ("nst×5",),
                  "pkt": ("pkt×500",), "fit": ("fitnets×1",)}
    seed_effect = rng.normal(0, 0.01, size=len(SEEDS))  # shared by every stage of a seed: the pairing
    values = {k: 0.3 + e + seed_effect + rng.normal(0, 0.008, size=len(SEEDS)) for k, e in effects.items()}
    results = {s: [fake(k, values[k][i], 0.5, values[k][i], val=0.2 + (0.01 if k == "kd_4" else 0.0),
                        objectives=objectives[k]) for k in effects] for i, s in enumerate(SEEDS)}
    return results, values


def test_the_family_is_the_methods_at_their_chosen_weights_and_holm_matches_statsmodels() -> None:
    results, values = _results(np.random.default_rng(0))
    rows = {r["stage"]: r for r in seed_rows(results, "none")}
    members = [k for k, r in rows.items() if "p_holm" in r]
    assert members == ["kd_4", "dist", "nst", "pkt", "fit"]  # kd ×1 lost on validation; the baseline is no member
    p = [stats.ttest_1samp(values[k] - values["none"], 0.0).pvalue for k in members]
    adjusted = multipletests(p, method="holm")[1]
    assert [rows[k]["p"] for k in members] == pytest.approx(p, rel=1e-9)
    assert [rows[k]["p_holm"] for k in members] == pytest.approx(list(adjusted), rel=1e-9)
    assert rows["kd_4"]["family"] == {"k": 5, "n": 6, "method": "max-t"}


def test_the_simultaneous_intervals_lie_between_the_per_method_and_bonferronis() -> None:
    results, values = _results(np.random.default_rng(1))
    rows = {r["stage"]: r for r in seed_rows(results, "none")}
    for k in ("kd_4", "dist", "nst", "pkt", "fit"):
        d = values[k] - values["none"]
        mean, se = d.mean(), d.std(ddof=1) / np.sqrt(len(d))
        per_method = stats.t.ppf(0.975, len(d) - 1) * se
        bonferroni = stats.t.ppf(1 - 0.025 / 5, len(d) - 1) * se
        low, high = rows[k]["sim_ci"]
        assert (low + high) / 2 == pytest.approx(mean, abs=1e-12)
        assert per_method < (high - low) / 2 <= bonferroni * 1.01, k  # max-t: at most Bonferroni (Monte Carlo)


def test_friedmans_ranks_match_scipy_and_follow_the_metrics_direction() -> None:
    results, values = _results(np.random.default_rng(2))
    rows = seed_rows(results, "none")
    ranked = family.ranks(rows, "none")
    order = ["none", "kd_4", "dist", "nst", "pkt", "fit"]
    scores = np.array([[values[k][i] for k in order] for i in range(len(SEEDS))])
    expected = stats.rankdata(-scores, axis=1).mean(axis=0)  # rank 1 = the best on a seed
    assert list(ranked["ranks"].values()) == pytest.approx(list(expected), rel=1e-12)
    chi2, p = stats.friedmanchisquare(*scores.T)  # continuous scores: no ties, scipy's correction is 1
    assert ranked["result"].chi2 == pytest.approx(chi2, rel=1e-10) and ranked["result"].p_chi2 == pytest.approx(p)
    for row in rows:  # a metric where lower is better ranks the other way round
        row["view"] = dataclasses.replace(row["view"], lower_is_better=True)
    flipped = family.ranks(rows, "none")
    assert list(flipped["ranks"].values()) == pytest.approx(list(len(order) + 1 - expected), rel=1e-12)


def test_the_report_names_the_family_and_draws_the_diagram(tmp_path: Path) -> None:
    results, _ = _results(np.random.default_rng(3))
    rows = seed_rows(results, "none")
    path = write_seeds_report(tmp_path, rows, "none", Console(file=open(tmp_path / "out.txt", "w")), stem="results")
    text = path.read_text()
    assert "| p Holm | simultaneous 95 % |" in text
    assert "Family: the 5 methods compared with the baseline" in text and "max-t" in text
    assert "## All methods at once, by rank" in text and "Nemenyi's critical difference at 0.05: CD = " in text
    assert (tmp_path / "results_cd.png").stat().st_size > 5_000
    kd_1 = next(line for line in text.splitlines() if line.startswith("| kd_1 |"))
    assert kd_1.rstrip(" |").endswith("— | —")  # a weight the validation did not choose: outside the family
    console = (tmp_path / "out.txt").read_text()
    assert "over the family of 5 methods at their chosen weights: Holm-adjusted p" in " ".join(console.split())


def test_the_family_forest_shows_each_method_at_its_chosen_weight_with_its_simultaneous_interval(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``results_family.png``: the family alone (kd ×1, which the validation did not choose, is not drawn), best
    first, each with a thick per-method and a thin simultaneous interval; linked from the chosen-weights section."""
    from distilkit.report import plots

    drawn: dict[str, list] = {}

    def keep(fig, path) -> None:  # the figure's rows and lines, before it is written
        (ax,) = fig.axes
        drawn[Path(path).name] = [[t.get_text() for t in ax.get_yticklabels()],
                                  [(line.get_linewidth(), tuple(line.get_xdata())) for line in ax.get_lines()]]
        real(fig, path)

    real = plots.save
    monkeypatch.setattr(plots, "save", keep)
    results, _ = _results(np.random.default_rng(3))
    rows = seed_rows(results, "none")
    text = write_seeds_report(tmp_path, rows, "none", Console(file=open(tmp_path / "out.txt", "w")),
                              stem="results").read_text()
    assert (tmp_path / "results_family.png").is_file()
    chosen = text.split("## Each method at the weight chosen on validation")[1].split("## Every variant")[0]
    assert "](results_family.png)" in chosen
    labels, lines = drawn["results_family.png"]
    by = {r["stage"]: r for r in rows}
    best_first = sorted(["kd_4", "dist", "nst", "pkt", "fit"], key=lambda k: -by[k]["delta_mean"])
    assert [t.split(" ")[0] for t in reversed(labels)] == best_first  # the top row is the best
    thick = sorted(tuple(round(v, 9) for v in x) for w, x in lines if w == 2.2)
    thin = sorted(tuple(round(v, 9) for v in x) for w, x in lines if w == 0.9)
    scale = by["dist"]["view"].main[2]
    assert thick == sorted(tuple(round(scale * v, 9) for v in by[k]["delta_ci"]) for k in best_first)
    assert thin == sorted(tuple(round(scale * v, 9) for v in by[k]["sim_ci"]) for k in best_first)
    assert len(drawn["results_forest.png"][0]) == 6  # the forest of every row keeps kd ×1


def test_no_family_without_two_methods() -> None:
    rng = np.random.default_rng(4)
    results = {s: [fake("none", *rng.uniform(0.1, 0.3, 3)), fake("kd", *rng.uniform(0.1, 0.3, 3),
                                                                 objectives=("kd×1",))] for s in SEEDS}
    rows = seed_rows(results, "none")
    assert family.of(rows) is None and not any("p_holm" in r for r in rows) and family.describe(rows) == ""
    assert family.ranks(rows, "none") is None  # two rows: nothing to rank


def _with_classes(results: dict, rng: np.random.Generator, names: list[str], voxels: list[int]) -> dict:
    """Each fake run given per-class test IoUs, the class names (class 0 = empty first) and the split's voxels."""
    ious = {}
    for seed, runs in results.items():
        for run in runs:
            iou = list(rng.uniform(0.0, 1.0, size=len(names)))
            if run.name == "dist":  # DIST lifts the second class on every seed
                iou[1] = ious[(seed, "none")][1] + 0.1 + 0.01 * rng.standard_normal()
            ious[(seed, run.name)] = iou
            run.summary["test"]["best"].update(class_iou=iou, class_voxels=voxels)
            run.summary["classes"] = {"names": ["empty", *names], "colours": []}
    return ious


@pytest.mark.plots
def test_per_class_differences_match_numpy_and_scipy_ordered_by_voxels(tmp_path: Path) -> None:
    from distilkit.report.classes import class_table

    rng = np.random.default_rng(5)
    results, _ = _results(rng)
    names, voxels = ["car", "road", "pole"], [500, 90_000, 40]
    ious = _with_classes(results, rng, names, voxels)
    rows = seed_rows(results, "none")
    table = class_table(rows, "none")
    assert table["classes"] == ["road", "car", "pole"]  # most voxels first
    assert table["voxels"] == pytest.approx([90_000 / 90_540, 500 / 90_540, 40 / 90_540])
    assert list(table["methods"]) == ["kd_4", "dist", "nst", "pkt", "fit"]  # the family
    for method, cells in table["methods"].items():
        for (mean, low, high), c in zip(cells, (1, 0, 2)):
            d = np.array([ious[(s, method)][c] - ious[(s, "none")][c] for s in SEEDS])
            half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
            assert (mean, low, high) == pytest.approx((d.mean(), d.mean() - half, d.mean() + half), rel=1e-9)
    assert table["methods"]["dist"][0][1] > 0  # road, lifted by DIST: its interval lies above 0
    write_seeds_report(tmp_path, rows, "none", Console(file=open(tmp_path / "out.txt", "w")), stem="results")
    text = (tmp_path / "results_classes.md").read_text()
    road = next(line for line in text.splitlines() if line.startswith("| road |"))
    assert road.split(" | ")[1] == "99.40 %" and road.split(" | ")[3].startswith("**+10.")  # DIST's column, bold
    assert (tmp_path / "results_classes.png").stat().st_size > 5_000
    assert "[results_classes.md](results_classes.md)" in (tmp_path / "results.md").read_text()
    assert "mean over 6 seeds with" in text and "| class | voxels | kd_4 | dist | nst |" in text  # all six: said once
    # a sweep not finished: a method over fewer seeds says so in its column, and the header gives the range
    short = seed_rows({s: r for s, r in results.items()}, "none")
    for row in short:
        if row["stage"] == "dist":
            row["class_iou"] = {s: v for s, v in row["class_iou"].items() if s < 4}
    part = class_table(short, "none")
    assert part["seeds"] == {"kd_4": 6, "dist": 4, "nst": 6, "pkt": 6, "fit": 6}
    from distilkit.report.classes import classes_markdown
    head = classes_markdown(part, "t", None).splitlines()
    assert "mean over the seeds each method shares with the baseline (4 to 6" in head[2]
    assert head[4].startswith("| class | voxels | kd_4 (6) | dist (4) |")


def test_no_per_class_table_without_class_scores(tmp_path: Path) -> None:
    results, _ = _results(np.random.default_rng(6))
    write_seeds_report(tmp_path, seed_rows(results, "none"), "none", Console(file=open(tmp_path / "o.txt", "w")),
                       stem="results")
    assert not (tmp_path / "results_classes.md").exists() and "results_classes" not in \
        (tmp_path / "results.md").read_text()
