"""A stage scores its best-validation checkpoint on its own only where that is not the last step: at the last step
the two are the same weights, evaluated once (distilkit/engine/train/stage.py, StageRun.score)."""

from __future__ import annotations

from pathlib import Path

from _no_run_reports import no_run_reports  # noqa: F401
from conftest import tiny_recipe


def test_a_best_checkpoint_at_the_last_step_is_scored_once(tmp_path: Path, monkeypatch) -> None:
    from distilkit.engine.train import stage as stage_module
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    real = stage_module.StageRun.evaluate
    calls: list[bool] = []  # per evaluation: whether it was of a loaded checkpoint's model

    def counted(self, dataset, model=None, scenes=False):
        calls.append(model is not None)
        return real(self, dataset, model, scenes)

    monkeypatch.setattr(stage_module.StageRun, "evaluate", counted)
    (result,) = Pipeline(recipe_from_dict(tiny_recipe(steps=1, distill=False)), tmp_path / "runs", quiet=True).run()
    summary = result.summary
    assert summary["best"]["step"] == summary["steps"] == 1  # validated at its only step: the best is the last
    assert summary["test"]["best_step"] == summary["test"]["last_step"] == 1
    assert summary["test"]["best"] == summary["test"]["last"]
    assert calls and not any(calls)  # no evaluation of best.pt's model: the last step's scores are its scores
