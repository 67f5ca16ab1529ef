"""Optimisation: registered optimizers and learning-rate schedules, frozen parameters, loss-weight warm-up."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.engine.train.optim import CosineParams, StepParams, cosine, lr_factor, step_decay, weight_factor
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.memory.probe import probe_trainer
from distilkit.engine.assemble.resolve import resolve
from distilkit.errors import DistilkitError, RecipeError
from distilkit.recipe import ScheduleSpec, recipe_from_dict
from distilkit.registry import SCHEDULES


def test_schedules_follow_their_formulas() -> None:
    assert [step_decay(s, 10, StepParams(step_size=3, gamma=0.5)) for s in range(7)] == \
        [1, 1, 1, 0.5, 0.5, 0.5, 0.25]
    p = CosineParams(min_factor=0.1)
    for s in range(11):
        assert cosine(s, 10, p) == pytest.approx(0.1 + 0.9 * (1 + math.cos(math.pi * s / 10)) / 2)
    warm = ScheduleSpec(name="cosine", warmup_steps=4)
    assert [lr_factor(warm, p, s, 10) for s in range(4)] == pytest.approx([cosine(s, 10, p) * (s + 1) / 4
                                                                           for s in range(4)])
    assert lr_factor(warm, p, 4, 10) == pytest.approx(cosine(4, 10, p))
    assert [weight_factor(4, s) for s in range(6)] == [0.25, 0.5, 0.75, 1.0, 1.0, 1.0] and weight_factor(0, 0) == 1


def _logged(run_dir: Path, key: str) -> list[float]:
    return [json.loads(x)[key] for x in (run_dir / "metrics.jsonl").read_text().splitlines() if key in json.loads(x)]


def test_a_run_steps_its_learning_rate_by_the_schedule_and_a_plugin_schedule_works_alike(tmp_path) -> None:
    r = tiny_recipe(steps=4, distill=False)
    r["stages"]["teacher"]["optimizer"] = {"name": "sgd", "lr": 0.1,
                                           "schedule": {"name": "step", "params": {"step_size": 2, "gamma": 0.5},
                                                        "warmup_steps": 2}}
    (res,) = Pipeline(recipe_from_dict(r), tmp_path / "a", quiet=True).run()
    assert _logged(res.run_dir, "lr") == pytest.approx([0.05, 0.1, 0.05, 0.05])  # warm-up 1/2, 2/2; then halved

    from distilkit.engine.train.optim import NoParams

    SCHEDULES.add("halving", lambda step, total, params: 0.5 ** step, description="test", paper="tests",
                  params=NoParams)  # a plugin's schedule, registered as a plugin does
    try:
        r["stages"]["teacher"]["optimizer"]["schedule"] = {"name": "halving"}
        (res,) = Pipeline(recipe_from_dict(r), tmp_path / "b", quiet=True).run()
        assert _logged(res.run_dir, "lr") == pytest.approx([0.1, 0.05, 0.025, 0.0125])
    finally:
        SCHEDULES.remove("halving")


def test_unknown_optimizers_and_schedules_and_bad_schedule_parameters_are_named(tmp_path) -> None:
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["teacher"]["optimizer"] = {"name": "adamm", "schedule": {"name": "cosin"}}
    with pytest.raises(RecipeError) as err:
        resolve(recipe_from_dict(r), "r")
    text = str(err.value)
    assert "stages.teacher.optimizer.name: unknown optimizer 'adamm'; did you mean 'adam'" in text
    assert "stages.teacher.optimizer.schedule.name: unknown schedule 'cosin'; did you mean 'cosine'" in text
    r["stages"]["teacher"]["optimizer"] = {"schedule": {"name": "step", "params": {"gamma": 0.5}}}
    with pytest.raises(RecipeError, match=r"stages.teacher.optimizer.schedule.params.step_size"):
        resolve(recipe_from_dict(r), "r")


def _trainer(tmp_path: Path, stage: dict) -> tuple:
    r = tiny_recipe(steps=2, distill=False)
    r["stages"]["teacher"].update(stage)
    res = resolve(recipe_from_dict(r), "r")
    trainer = probe_trainer(res, "teacher", res.data_params, tmp_path)
    return trainer, trainer.first_batch()


@pytest.mark.parametrize("how", ["freeze", "lr_scale"])
def test_frozen_parameters_stay_as_they_are_and_the_rest_trains(tmp_path, how: str) -> None:
    stage = ({"freeze": ["student.net.completion.*"]} if how == "freeze" else
             {"optimizer": {"param_groups": [{"match": "student.net.completion.*", "lr_scale": 0}]}})
    trainer, batch = _trainer(tmp_path, stage)
    named = dict(trainer._named_parameters())
    frozen = {n for n in named if n.startswith("student.net.completion.")}
    assert frozen and all(not named[n].requires_grad for n in frozen)
    before = {n: p.detach().clone() for n, p in named.items()}
    trainer.student.train()
    for step in range(2):
        trainer.train_step(batch, step)
    in_optimizer = {id(p) for g in trainer.optimizer.param_groups for p in g["params"]}
    assert not any(id(named[n]) in in_optimizer for n in frozen)
    assert all(torch.equal(named[n], before[n]) for n in frozen)
    assert any(not torch.equal(named[n], before[n]) for n in named if n not in frozen)


def test_a_freeze_glob_that_matches_nothing_is_an_error(tmp_path) -> None:
    with pytest.raises(DistilkitError, match=r"freeze 'student.nett.\*' matches no parameter \(names look like "
                                             r"student\.net\."):
        _trainer(tmp_path, {"freeze": ["student.nett.*"]})


def test_a_terms_weight_warms_up_linearly(tmp_path) -> None:
    trainer, batch = _trainer(tmp_path, {"task_losses": [{"name": "ce", "warmup_steps": 4}, {"name": "lovasz"}]})
    trainer.student.eval()  # the same forward twice
    values = {}
    for step in (0, 3):
        trainer._step = step
        with torch.no_grad():
            values[step] = {k: float(v) for k, v in trainer.loss_terms(batch).items()}
    assert values[0]["ce"] == pytest.approx(0.25 * values[3]["ce"], rel=1e-6)
    assert values[0]["lovasz"] == pytest.approx(values[3]["lovasz"], rel=1e-6)  # no warm-up: its full weight
