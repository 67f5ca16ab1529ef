"""Mixed precision: models under autocast, loss terms in float32, fp32 stages keep their identity."""

from __future__ import annotations

import math

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.engine.train.pipeline import Pipeline
from distilkit.objectives.dskd import DSKD
from distilkit.recipe import recipe_from_dict


def hashes(tmp_path, precision: str | None) -> dict[str, str]:
    r = tiny_recipe()
    if precision is not None:
        for stage in r["stages"].values():
            stage["train"]["precision"] = precision
    return Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).hashes


def test_fp32_adds_nothing_to_the_identity_and_bf16_is_a_different_stage(tmp_path) -> None:
    assert hashes(tmp_path, None) == hashes(tmp_path, "fp32")
    assert hashes(tmp_path, "bf16")["teacher"] != hashes(tmp_path, None)["teacher"]


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_reduced_precision_runs_the_models_in_it_and_the_terms_in_float32(tmp_path, monkeypatch, precision) -> None:
    seen: dict[str, set] = {"dskd": set()}
    orig = DSKD.forward

    def spy(self, student, teacher, batch):
        seen["dskd"].add((student.feats.dtype, teacher.feats.dtype))
        return orig(self, student, teacher, batch)

    monkeypatch.setattr(DSKD, "forward", spy)
    r = tiny_recipe(steps=2)
    for stage in r["stages"].values():
        stage["train"]["precision"] = precision
    pipe = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    from distilkit.engine.train import trainer as trainer_module

    dtypes = set()
    orig_loss_terms = trainer_module.Trainer.loss_terms

    def loss_terms(self, batch):
        with self._autocast():
            dtypes.add(self.student(batch)["logits"].dtype)
        return orig_loss_terms(self, batch)

    monkeypatch.setattr(trainer_module.Trainer, "loss_terms", loss_terms)
    results = pipe.run()
    want = torch.bfloat16 if precision == "bf16" else torch.float16
    assert dtypes == {want}  # the model ran in reduced precision
    assert seen["dskd"] == {(torch.float32, torch.float32)}  # the objective got float32 taps
    assert all(r.summary["status"] == "finished" for r in results)
    assert all(math.isfinite(r.summary["test"]["best"]["miou"]) for r in results)
