"""Control teachers (issue 59, item 3): ``teacher: {control: random | shuffled}`` carries no knowledge of the sample —
the shuffled teacher's outputs are the real teacher's outputs for another sample (a permutation of the real ones,
no sample meeting its own), the random teacher's weights are not the checkpoint's; validate refuses the controls
that could not work, and a sweep file adds the control rows with one line."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from conftest import tiny_recipe
from distilkit.engine.train.controls import control_seed, cycle
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import DataError, RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.weights import load_checkpoint

AUGMENT = {"flip": ["x", "y"], "rotate90": "z"}


@pytest.mark.parametrize("n", [2, 3, 7, 50])
def test_the_shuffle_is_one_cycle_through_every_sample(n) -> None:
    sigma = cycle(n, seed=3)
    assert sorted(sigma) == list(range(n)) and all(sigma[i] != i for i in range(n))
    seen, i = [], 0  # followed from 0, the cycle visits every sample once before it returns
    for _ in range(n):
        seen.append(i)
        i = sigma[i]
    assert i == 0 and sorted(seen) == list(range(n))
    assert cycle(n, seed=3) == sigma and (n < 4 or cycle(n, seed=4) != sigma)


def test_sattolos_cycles_are_uniform_over_the_cycles() -> None:
    """All (n-1)! = 6 four-cycles appear, each about 1/6 of the time (an independent count, not the algorithm)."""
    counts: dict[tuple[int, ...], int] = {}
    for seed in range(3000):
        key = tuple(cycle(4, seed))
        counts[key] = counts.get(key, 0) + 1
    assert len(counts) == 6 and all(abs(c / 3000 - 1 / 6) < 0.03 for c in counts.values())


def test_a_shuffle_needs_two_samples() -> None:
    with pytest.raises(DataError, match="needs two at least"):
        cycle(1, 0)


def _recipe(control: str | None, n_train: int = 4, augment: dict | None = AUGMENT, store: bool = False) -> dict:
    recipe = tiny_recipe(steps=1)
    recipe["data"]["params"]["num_train"] = n_train
    student = recipe["stages"]["student"]
    student["train"]["augment"] = augment
    student["teacher"] = {"from": "teacher", **({"control": control} if control else {}),
                          **({"store": True} if store else {})}
    return recipe


def _built(tmp_path, recipe: dict):
    """The student stage's trainer as its run builds it, after its teacher has trained."""
    from distilkit.engine.train.stage import StageRun

    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    pipe.run(only=["teacher"])
    run = StageRun(pipe, "student", pipe.run_dir("student"))
    return pipe, run, run.build()


def test_the_shuffled_teacher_gives_each_sample_the_real_teachers_outputs_for_its_partner(tmp_path) -> None:
    """Every step of an epoch: the teacher outputs the terms read for sample i under draw d are the checkpoint's
    outputs for σ(i) under d, computed here independently, and never those for i itself."""
    from distilkit.data.augment import Augmentation
    from distilkit.engine.assemble.runs import load_run

    pipe, run, trainer = _built(tmp_path, _recipe("shuffled"))
    stage = pipe.resolved.stages["student"]
    teacher = load_run(pipe.weights("teacher"), model=stage.teacher, info=pipe.resolved.data_info, role="teacher")
    aug = Augmentation(stage.spec.train.augment, pipe.resolved.data_info.grid)
    split = pipe.dataset("train")
    sigma = cycle(len(split), run.seed)
    used = []
    for step in range(trainer.plan.steps_per_epoch):
        ((i, d),) = trainer.plan.items(step)
        batch = trainer.prepare(trainer.plan.batch(trainer.train_set, trainer.collate, step))
        assert batch.meta["sample_id"] == [split.sample_id(i)]  # the student still reads its own sample
        got = trainer._teacher_outputs(batch)["completion"]
        with torch.no_grad():
            partner = teacher(pipe.collate([aug.apply(split[sigma[i]], d)]))["completion"]
            own = teacher(pipe.collate([aug.apply(split[i], d)]))["completion"]
        assert torch.equal(got.coords, partner.coords) and torch.equal(got.feats, partner.feats)
        assert got.coords.shape != own.coords.shape or not torch.equal(got.feats, own.feats)
        used.append(sigma[i])
    assert sorted(used) == list(range(len(split)))  # an epoch reads each real output once: a permutation of them


def test_a_shuffled_student_from_the_store_equals_the_live_shuffled_one_bit_for_bit(tmp_path) -> None:
    """The store path reads the partner's rows of the real teacher's store: the same student, bit for bit; the
    shuffled student shares the store of the real teacher (one store for both)."""
    recipe = _recipe("shuffled", n_train=3)
    stages = recipe["stages"]
    stages["student"]["train"]["steps"] = 3
    stages["student_stored"] = copy.deepcopy(stages["student"])
    stages["student_stored"]["teacher"]["store"] = True
    stages["real_stored"] = copy.deepcopy(stages["student_stored"])
    del stages["real_stored"]["teacher"]["control"]
    results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()}
    live, stored, real = (load_checkpoint(results[n].run_dir / "checkpoints" / "last.pt")["student"]
                          for n in ("student", "student_stored", "real_stored"))
    assert all(torch.equal(live[k], stored[k]) for k in live)
    assert any(not torch.equal(live[k], real[k]) for k in live)  # the control is not the real teacher
    assert len(list((tmp_path / "runs" / "tiny").glob("teacher-store-*"))) == 1
    assert results["student"].summary["teacher_control"] == "shuffled"
    assert results["real_stored"].summary["teacher_control"] is None


def test_the_random_teacher_has_the_architecture_and_not_the_checkpoints_weights(tmp_path) -> None:
    pipe, run, trainer = _built(tmp_path, _recipe("random"))
    checkpoint = load_checkpoint(pipe.weights("teacher"))["student"]
    mine = trainer.teacher.state_dict()
    assert set(mine) == set(checkpoint) and all(mine[k].shape == checkpoint[k].shape for k in mine)
    weights = [k for k in mine if mine[k].is_floating_point() and mine[k].dim() >= 2]  # convolutions, linears
    assert weights and all(not torch.equal(mine[k], checkpoint[k]) for k in weights)
    assert not trainer.teacher.training and not any(p.requires_grad for p in trainer.teacher.parameters())
    again = _built(tmp_path / "again", _recipe("random"))[2].teacher.state_dict()  # seeded: the same draw
    assert all(torch.equal(mine[k], again[k]) for k in mine)
    assert control_seed(run.seed) != run.seed


def test_a_random_teacher_of_the_students_architecture_is_not_the_students_initialisation(tmp_path) -> None:
    recipe = _recipe("random", augment=None)
    recipe["stages"]["teacher"]["model"]["params"]["frames"] = 1  # one architecture for both
    _, _, trainer = _built(tmp_path, recipe)
    student, teacher = trainer.student.state_dict(), trainer.teacher.state_dict()
    weights = [k for k in student if student[k].is_floating_point() and student[k].dim() >= 2]  # the drawn ones
    assert all(not torch.equal(student[k], teacher[k]) for k in weights)


@pytest.mark.parametrize("teacher, words", [
    ({"ema": True, "control": "random"}, "a control needs a teacher of its own"),
    ({"from": "teacher", "control": "random", "store": True}, "a random one runs live"),
    ({"from": "teacher", "control": "noise"}, "'random' or 'shuffled'"),
])
def test_the_recipe_refuses_a_control_that_cannot_work(teacher, words) -> None:
    recipe = tiny_recipe(steps=1)
    recipe["stages"]["student"]["teacher"] = teacher
    with pytest.raises(RecipeError, match=words):
        recipe_from_dict(recipe)


def test_validate_refuses_a_shuffled_control_for_a_term_that_calls_the_teacher(capsys) -> None:
    from distilkit.cli import main

    assert main(["validate", "--static", "recipes/scorelidar.yaml", "--set",
                 "stages.student.teacher.control=shuffled"]) == 2
    assert "calls the teacher's predict_noise() on the sample's own input" in capsys.readouterr().err


def test_a_sweep_file_adds_the_control_rows_with_one_line(tmp_path) -> None:
    from distilkit.sweep.spec import load_sweep

    (tmp_path / "r.yaml").write_text(__import__("yaml").safe_dump(tiny_recipe(steps=1)))
    (tmp_path / "s.yaml").write_text("name: s\nrecipe: r.yaml\nstage: student\nteacher: teacher\n"
                                     "controls: [shuffled, random]\nvariants:\n  none: {distill: []}\n"
                                     "  dskd: {label: DSKD}\n  kd: {distill: [{name: kd}], controls: false}\n")
    sweep = load_sweep(tmp_path / "s.yaml")
    assert list(sweep.spec.variants) == ["none", "dskd", "dskd.shuffled", "dskd.random", "kd"]
    for kind in ("shuffled", "random"):
        stage = sweep.recipes[f"dskd.{kind}"].stages[f"dskd.{kind}"]
        assert stage.teacher.control == kind and stage.teacher.from_ == "teacher"
        assert [t.name for t in stage.distill] == ["dskd"] and sweep.label(f"dskd.{kind}") == f"DSKD · {kind} teacher"
    assert sweep.recipes["dskd"].stages["dskd"].teacher.control is None
    assert sweep.controls == {"dskd.shuffled": ("dskd", "shuffled"), "dskd.random": ("dskd", "random")}


def test_the_control_seed_is_a_stream_of_its_own() -> None:
    assert len({control_seed(s) for s in range(100)}) == 100
    assert np.random.default_rng(control_seed(0)).random() != np.random.default_rng(0).random()


def _rows_with_controls(rng: np.random.Generator):
    """Six seeds of a baseline, two methods (one at two weights) and their shuffled and random controls."""
    from test_seeds import fake

    seeds = range(6)
    effects = {"none": 0.0, "kd_1": 0.01, "kd_4": 0.02, "kd_1.shuffled": 0.0, "kd_4.shuffled": 0.015,
               "kd_4.random": 0.0, "dist": 0.02, "dist.shuffled": 0.02}
    shared = rng.normal(0, 0.01, size=6)
    values = {k: 0.3 + e + shared + rng.normal(0, 0.004, size=6) for k, e in effects.items()}
    results = {}
    for i in seeds:
        results[i] = []
        for k in effects:
            obj = () if k == "none" else (("dist×1",) if k.startswith("dist") else (f"kd×{k[3]}",))
            r = fake(k, values[k][i], 0.5, values[k][i], val=0.2 + (0.01 if k.startswith("kd_4") else 0.0),
                     objectives=obj)
            r.summary["teacher_control"] = k.split(".")[1] if "." in k else None
            results[i].append(r)
    return results, values


def test_each_method_is_compared_with_its_controls_and_the_controls_are_no_methods() -> None:
    from scipy import stats
    from statsmodels.stats.multitest import multipletests

    from distilkit.report.seeds import seed_rows

    results, values = _rows_with_controls(np.random.default_rng(0))
    rows = {r["stage"]: r for r in seed_rows(results, "none")}
    assert [k for k, r in rows.items() if "p_holm" in r] == ["kd_4", "dist"]  # the family: methods, chosen weights
    assert rows["kd_4.shuffled"]["control_of"] == "kd_4" and rows["kd_4.shuffled"]["chosen"]
    assert not rows["kd_1.shuffled"]["chosen"]  # its method lost on validation
    compared = [("kd_4", "shuffled"), ("kd_4", "random"), ("dist", "shuffled")]
    for method, kind in compared:
        e = rows[method]["vs_control"][kind]
        d = values[method] - values[f"{method}.{kind}"]
        assert e["delta"] == pytest.approx(list(d)) and e["mean"] == pytest.approx(d.mean())
        half = stats.t.ppf(0.975, 5) * d.std(ddof=1) / np.sqrt(6)
        assert e["ci"] == pytest.approx((d.mean() - half, d.mean() + half), rel=1e-9)
    p = [stats.ttest_1samp(values[m] - values[f"{m}.{k}"], 0.0).pvalue for m, k in compared]
    assert [rows[m]["vs_control"][k]["p_holm"] for m, k in compared] == pytest.approx(
        list(multipletests(p, method="holm")[1]), rel=1e-9)
    assert "p_holm" not in rows["kd_1"]["vs_control"]["shuffled"]  # not chosen: outside the Holm family


def test_the_report_has_a_section_against_the_controls(tmp_path) -> None:
    from rich.console import Console

    from distilkit.report.seeds import seed_rows, write_seeds_report

    results, _ = _rows_with_controls(np.random.default_rng(1))
    rows = seed_rows(results, "none")
    text = write_seeds_report(tmp_path, rows, "none", Console(file=__import__("io").StringIO()),
                              stem="results").read_text()
    section = text[text.index("## Against the control teachers"):]
    assert "over the 3 comparisons of the methods at their chosen weights" in section
    lines = [line for line in section.splitlines() if line.startswith("| kd_4") or line.startswith("| dist")]
    assert [line.split(" | ")[1] for line in lines] == ["shuffled", "random", "shuffled"]
    assert len([line for line in section.splitlines() if line.startswith("| kd_1")]) == 1


def test_a_sweep_adds_only_the_controls_a_variant_can_take(tmp_path) -> None:
    """A stored teacher's random row runs live (no store); a term that calls the teacher gets no shuffled row;
    an `ema: {}` teacher (the student's own) gets none; every row sits after its variant."""
    import yaml

    from distilkit.sweep.spec import load_sweep

    recipe = tiny_recipe(steps=1)
    recipe["stages"]["student"]["teacher"]["store"] = True
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    (tmp_path / "s.yaml").write_text("name: s\nrecipe: r.yaml\nstage: student\nteacher: teacher\n"
                                     "controls: [random, shuffled]\nvariants:\n  dskd: {}\n  none: {distill: []}\n"
                                     "  kd: {distill: [{name: kd}]}\n")
    sweep = load_sweep(tmp_path / "s.yaml")
    assert list(sweep.recipes) == ["dskd", "dskd.random", "dskd.shuffled", "none", "kd", "kd.random", "kd.shuffled"]
    assert sweep.recipes["dskd.random"].stages["dskd.random"].teacher.store is None
    assert sweep.recipes["dskd.shuffled"].stages["dskd.shuffled"].teacher.store is not None  # the real one's store
    (tmp_path / "s2.yaml").write_text("name: s2\nrecipe: r.yaml\nstage: student\nteacher: teacher\n"
                                      "controls: [shuffled, random]\nvariants:\n  vsd: {distill: [{name: vsd}]}\n")
    assert list(load_sweep(tmp_path / "s2.yaml").controls) == ["vsd.random"]  # VSD calls the teacher itself
    own = tiny_recipe(steps=1)
    own["stages"]["student"]["teacher"] = {"ema": {}}
    (tmp_path / "r3.yaml").write_text(yaml.safe_dump(own))
    (tmp_path / "s3.yaml").write_text("name: s3\nrecipe: r3.yaml\nstage: student\ncontrols: [random]\n"
                                      "variants:\n  dskd: {}\n")
    assert load_sweep(tmp_path / "s3.yaml").controls == {}
