"""Several seeds of one recipe: mean ± sample std per stage and paired differences to a baseline."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.cli import main
from distilkit.engine.assemble.resolve import resolve
from distilkit.report.seeds import default_baseline, seed_rows
from distilkit.recipe import recipe_from_dict


def fake(stage: str, miou: float, iou: float, last: float, val: float = 0.2,
         objectives: tuple[str, ...] = ()) -> SimpleNamespace:
    summary = {"stage": stage, "label": stage, "adapter": "scpnet", "objectives": list(objectives), "input": "1 frame",
               "test": {"best": {"miou": miou, "iou": iou}, "last": {"miou": last, "iou": iou}, "best_step": 5},
               "best": {"step": 5, "scores": {"miou": val, "iou": iou}}, "report_split": "test"}
    return SimpleNamespace(name=stage, summary=summary, reused=False)


def test_mean_std_and_paired_differences_match_numpy() -> None:
    rng = np.random.default_rng(0)
    values = {stage: rng.uniform(0.1, 0.3, size=(3, 3)) for stage in ("plain", "kd", "dskd")}
    results = {seed: [fake(stage, *values[stage][i]) for stage in values] for i, seed in enumerate((0, 4, 7))}
    rows = {r["stage"]: r for r in seed_rows(results, "plain")}
    assert list(rows) == ["plain", "kd", "dskd"]
    for stage, v in values.items():
        row = rows[stage]
        assert row["seeds"] == [0, 4, 7]
        assert row["main_mean"] == pytest.approx(v[:, 0].mean())
        assert row["main_std"] == pytest.approx(v[:, 0].std(ddof=1))
        assert row["second_std"] == pytest.approx(v[:, 1].std(ddof=1))
        assert row["last_main_mean"] == pytest.approx(v[:, 2].mean())
    paired = values["dskd"][:, 0] - values["plain"][:, 0]
    assert rows["dskd"]["delta"] == pytest.approx(list(paired))
    assert rows["dskd"]["delta_std"] == pytest.approx(paired.std(ddof=1))
    assert rows["plain"]["delta"] == []  # no difference of the baseline to itself
    # 95 % interval: mean ± t(0.975, 2) s / sqrt(3), with t(0.975, 2) = 4.302653 from a printed t table
    half = 4.302653 * paired.std(ddof=1) / np.sqrt(3)
    assert rows["dskd"]["delta_ci"] == pytest.approx((paired.mean() - half, paired.mean() + half), rel=1e-6)


def test_report_compare_pairs_each_stage_with_its_own_reference(tmp_path: Path) -> None:
    """A few-step student against the undistilled teacher at its own step count (recipes/scorelidar.yaml)."""
    from distilkit.report.seeds import seeds_markdown

    rng = np.random.default_rng(1)
    stages = ("teacher_1", "teacher_8", "student_1", "student_8")
    values = {stage: rng.uniform(0.1, 0.3, size=(3, 3)) for stage in stages}
    results = {seed: [fake(stage, *values[stage][i]) for stage in stages] for i, seed in enumerate((0, 1, 2))}
    compare = {"student_1": "teacher_1", "student_8": "teacher_8"}
    rows = {r["stage"]: r for r in seed_rows(results, "teacher_8", compare)}
    for student, teacher in compare.items():
        assert rows[student]["delta"] == pytest.approx(list(values[student][:, 0] - values[teacher][:, 0]))
        assert rows[student]["reference"] == teacher
    assert rows["teacher_1"]["delta"] == pytest.approx(list(values["teacher_1"][:, 0] - values["teacher_8"][:, 0]))
    assert rows["teacher_8"]["delta"] == [] and rows["teacher_8"]["reference"] is None
    # stages without distillation are not weights of one method: none is "chosen" over another
    assert all(r["chosen"] and r["alternatives"] == 1 for r in rows.values())
    md = seeds_markdown(list(rows.values()), "teacher_8", "t")
    assert "| Δ to |" in md and "| teacher_1 |" in md and "report.compare" in md
    assert "Δ to" not in seeds_markdown(list(seed_rows(results, "teacher_8")), "teacher_8", "t")
    with pytest.raises(Exception, match="report.compare: 'nope' is not a stage"):
        recipe_from_dict({**tiny_recipe(), "report": {"compare": {"nope": "teacher"}}})


def test_t_interval_against_tabulated_quantiles() -> None:
    from distilkit.report.seeds import t_interval

    for n, t in ((2, 12.706205), (5, 2.776445), (30, 2.045230)):  # t(0.975, n - 1) from a printed table
        xs = list(np.linspace(-1.0, 2.0, n) ** 2)
        half = t * np.std(xs, ddof=1) / np.sqrt(n)
        assert t_interval(xs) == pytest.approx((np.mean(xs) - half, np.mean(xs) + half), rel=1e-6)
    assert all(np.isnan(t_interval([0.3])))  # one value: no interval


def test_a_stage_missing_in_one_seed_is_paired_only_where_both_ran() -> None:
    results = {0: [fake("plain", 0.2, 0.5, 0.2), fake("kd", 0.25, 0.5, 0.25)], 1: [fake("plain", 0.1, 0.5, 0.1)]}
    rows = {r["stage"]: r for r in seed_rows(results, "plain")}
    assert rows["kd"]["seeds"] == [0] and rows["kd"]["delta"] == pytest.approx([0.05])
    assert np.isnan(rows["kd"]["main_std"])  # one seed: no spread, shown without ±


def test_default_baseline_is_the_plain_student() -> None:
    r = tiny_recipe()
    r["stages"]["plain"] = {**r["stages"]["student"]}
    del r["stages"]["plain"]["distill"], r["stages"]["plain"]["teacher"]
    assert default_baseline(resolve(recipe_from_dict(r), "test")) == "plain"
    assert default_baseline(resolve(recipe_from_dict(tiny_recipe()), "test")) is None  # teacher + distilled only


def test_cli_runs_each_seed_and_writes_the_table(tmp_path: Path, capsys) -> None:
    r = tiny_recipe(steps=1)
    r["stages"]["plain"] = {k: v for k, v in r["stages"]["student"].items() if k not in ("distill", "teacher")}
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(r))
    out = tmp_path / "runs"
    assert main(["run", str(recipe), "-o", str(out), "-q", "--seed", "0", "1"]) == 0
    text = (out / "tiny" / "seeds.md").read_text()
    assert "seeds 0, 1" in text and "paired difference" in text and "'plain'" in text
    main_table, ranked = text.split("## All methods at once, by rank")  # two methods and the baseline: ranks too
    table = [line for line in main_table.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert "| row | average rank |" in ranked and (out / "tiny" / "seeds_cd.png").is_file()
    assert sorted(line.split(" | ")[0].strip("| ") for line in table) == ["plain", "student", "teacher"]
    assert all(" ± " in line for line in table)
    assert len(list((out / "tiny").glob("student-*"))) == 2  # one run per seed
    # a baseline that is not a stage, a repeated seed, a baseline without seeds: one line each
    capsys.readouterr()
    assert main(["run", str(recipe), "-o", str(out), "-q", "--seed", "0", "1", "--baseline", "plian"]) == 2
    assert "did you mean 'plain'" in capsys.readouterr().err
    assert main(["run", str(recipe), "-o", str(out), "-q", "--seed", "0", "0"]) == 2
    assert "each seed once" in capsys.readouterr().err
    assert main(["run", str(recipe), "-o", str(out), "-q", "--baseline", "plain"]) == 2
    assert "several seeds" in capsys.readouterr().err


def test_seed_tables_follow_the_stage_metric_not_ssc(tmp_path: Path) -> None:
    """A stage scored by a metric that is not installed now (a plugin's): its own keys, unscaled."""
    from rich.console import Console

    from distilkit.report.seeds import write_seeds_report

    def point(stage: str, chamfer: float) -> SimpleNamespace:
        summary = {"stage": stage, "label": stage, "adapter": "points", "objectives": [],
                   "metric": {"name": "gone-plugin", "key": "chamfer"},
                   "test": {"best": {"chamfer": chamfer}, "last": {"chamfer": chamfer}, "best_step": 2},
                   "report_split": "test"}
        return SimpleNamespace(name=stage, summary=summary, reused=False)

    results = {0: [point("plain", 0.30), point("kd", 0.20)], 1: [point("plain", 0.40), point("kd", 0.35)]}
    rows = {r["stage"]: r for r in seed_rows(results, "plain")}
    assert rows["kd"]["main"] == [0.20, 0.35] and rows["kd"]["delta"] == pytest.approx([-0.10, -0.05])
    path = write_seeds_report(tmp_path, list(rows.values()), "plain", Console(file=open(tmp_path / "out.txt", "w")))
    text = path.read_text()
    assert "| test chamfer best |" in text and "Δ test chamfer" in text and "-0.075 ± 0.035" in text and "mIoU" not in text


@pytest.mark.plots
def test_weights_are_chosen_on_validation_never_on_test(tmp_path: Path) -> None:
    """Two weights of DSKD: the one with the better mean validation mIoU is chosen even though the other has the
    better test mIoU; a method tried at one weight is its own choice; the report leads with the chosen rows, says
    what the seeds can resolve and draws the paired differences with their intervals."""
    from rich.console import Console

    from distilkit.report.seeds import write_seeds_report

    rows_in = {  # stage: (test mIoU per seed, val mIoU per seed, objectives)
        "none": ([0.30, 0.32, 0.31], [0.29, 0.30, 0.30], ()),
        "dskd_300": ([0.36, 0.37, 0.35], [0.30, 0.31, 0.30], ("dskd×300",)),  # best on test
        "dskd_3000": ([0.33, 0.34, 0.33], [0.33, 0.34, 0.32], ("dskd×3000",)),  # best on validation
        "kd": ([0.31, 0.30, 0.32], [0.30, 0.29, 0.31], ("kd×1",)),
    }
    results = {seed: [fake(stage, test[i], 0.5, test[i], val[i], objs) for stage, (test, val, objs) in rows_in.items()]
               for i, seed in enumerate((0, 1, 2))}
    rows = {r["stage"]: r for r in seed_rows(results, "none")}
    assert rows["dskd_3000"]["chosen"] and not rows["dskd_300"]["chosen"]
    assert rows["kd"]["chosen"] and rows["none"]["chosen"] and rows["dskd_300"]["alternatives"] == 2
    assert rows["dskd_3000"]["val_mean"] == pytest.approx(np.mean(rows_in["dskd_3000"][1]))
    assert rows["dskd_3000"]["val_std"] == pytest.approx(np.std(rows_in["dskd_3000"][1], ddof=1))
    path = write_seeds_report(tmp_path, list(rows.values()), "none", Console(file=open(tmp_path / "o.txt", "w")))
    text = path.read_text()
    chosen_table = text.split("## Each method at the weight chosen on validation")[1].split("## Every variant")[0]
    assert "dskd_3000 ◆" in chosen_table and "dskd_300 " not in chosen_table and "| kd |" in chosen_table
    assert "| val mIoU (selects) | test mIoU best |" in text and "Power: with 3 seeds" in text
    assert (tmp_path / "seeds_forest.png").stat().st_size > 1000 and "seeds_forest.png" in text


def test_detectable_effect_is_the_normal_theory_approximation() -> None:
    from distilkit.report.seeds import detectable_effect

    # t(0.975, 7) = 2.364624 and t(0.80, 7) = 0.896030 (a printed t table: 2.365 and 0.896)
    assert detectable_effect(1.5, 8) == pytest.approx((2.364624 + 0.896030) * 1.5 / np.sqrt(8), rel=1e-5)
    assert detectable_effect(1.5, 16) < detectable_effect(1.5, 8) < detectable_effect(3.0, 8)
    assert np.isnan(detectable_effect(1.0, 1))
