"""The stage run's loop: loaders with workers, resumable batch order, lifecycle hooks, further metrics, TensorBoard."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.engine.train.distributed import World
from distilkit.weights import load_checkpoint
from distilkit.engine.train.loader import BatchPlan, eval_indices, train_batches
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict


def run(tmp_path: Path, recipe: dict, folder: str, **kwargs: Any) -> list:
    return Pipeline(recipe_from_dict(recipe), tmp_path / folder, quiet=True).run(**kwargs)


def weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(run_dir / "checkpoints" / "last.pt")["student"]


def test_the_batch_plan_is_a_function_of_seed_and_step_and_shards_every_sample_once() -> None:
    plan = BatchPlan(size=7, batch_size=3, seed=5)
    assert plan.steps_per_epoch == 3
    for epoch in range(2):  # each epoch is a permutation of the split, the last batch smaller
        seen = [j for s in range(3) for j in plan.indices(epoch * 3 + s)]
        assert sorted(seen) == list(range(7)) and len(plan.indices(epoch * 3 + 2)) == 1
    assert plan.indices(0) != plan.indices(3)  # another epoch, another order
    g = torch.Generator().manual_seed(5 * 100_003 + 1)  # epoch 1, written out
    assert plan.indices(4) == [int(j) for j in torch.randperm(7, generator=g)[3:6]]
    halves = [BatchPlan(7, 4, 5, World(r, 2)).indices(0) for r in range(2)]
    assert sorted(halves[0] + halves[1]) == sorted(BatchPlan(7, 4, 5).indices(0)) and halves[0][0] != halves[1][0]
    blocks = [eval_indices(10, World(r, 3)) for r in range(3)]
    assert sum(blocks, []) == list(range(10))  # contiguous, in rank order, each sample once


@pytest.mark.parametrize("workers", [0, 2])
def test_the_loader_resumes_at_any_step_with_the_same_batches(workers: int) -> None:
    data = [{"x": i} for i in range(10)]

    def collate(samples: list[dict]) -> Any:
        from distilkit.data.batch import Batch

        return Batch({"x": torch.tensor([s["x"] for s in samples])}, {}, {"size": len(samples)})

    plan = BatchPlan(10, 4, 3)
    whole = [b.inputs["x"].tolist() for b in train_batches(data, plan, collate, 0, 9, workers)]
    assert whole == [plan.indices(s) for s in range(9)]
    assert [b.inputs["x"].tolist() for b in train_batches(data, plan, collate, 4, 9, workers)] == whole[4:]


def test_two_loader_workers_give_the_same_numbers_as_none_and_a_stop_mid_epoch_resumes_to_them(tmp_path,
                                                                                           monkeypatch) -> None:
    """Teacher and student, 4 steps each, with 0 and 2 loader workers: the same run folders, test scores and
    weights; a run with workers stopped after step 3 and started again ends the same too. (The run and recipe
    reports, which nothing here reads, are not written; tests/test_reports.py tests them.) Over 3 s: four pipelines
    of two stages, three of them with loader processes, are its point."""
    import distilkit.report.run

    monkeypatch.setattr(distilkit.report.run, "write_run_report", lambda run_dir: None)
    recipe = tiny_recipe(steps=4)
    for stage in recipe["stages"].values():
        stage["train"].update(checkpoint_every=1, eval_every=4)
    # 2 training scenes, batch 1: epochs of 2 steps, so the step after the stop (the 4th) is the second of the
    # second epoch: the resumed loader starts mid-epoch
    assert len(Pipeline(recipe_from_dict(recipe), tmp_path / "a", quiet=True).dataset("train")) == 2
    outcomes = {}
    for workers in (0, 2):
        for stage in recipe["stages"].values():
            stage["train"]["workers"] = workers
        outcomes[workers] = run(tmp_path, recipe, f"w{workers}", report=False)
    # a third run with workers stops after 3 steps (in the second epoch) and is started again
    run(tmp_path, recipe, "resumed", stop_after=3, report=False)
    assert load_checkpoint(next((tmp_path / "resumed").glob("tiny/teacher-*")) / "checkpoints" / "last.pt")["step"] == 3
    outcomes["resumed"] = run(tmp_path, recipe, "resumed", report=False)
    base = outcomes[0]
    for other in (outcomes[2], outcomes["resumed"]):
        for a, b in zip(base, other):
            assert a.run_dir.name == b.run_dir.name  # workers are not part of a stage's identity
            assert a.summary["test"]["best"] == {**b.summary["test"]["best"],
                                                 "seconds_per_sample": a.summary["test"]["best"]["seconds_per_sample"]}
            wa, wb = weights(a.run_dir), weights(b.run_dir)
            assert all(torch.equal(wa[k], wb[k]) for k in wa)


class Recorder:
    """A plugin's hook: what the loop showed it, moment by moment."""

    events: list[tuple[str, int]] = []

    def __init__(self, params: Any) -> None:
        self.params = params

    def before_train(self, loop: Any) -> None:
        Recorder.events.append(("before_train", loop.step))

    def before_step(self, loop: Any) -> None:
        Recorder.events.append(("before_step", loop.step))

    def after_step(self, loop: Any) -> None:
        assert "loss" in loop.values and loop.run_dir.is_dir()
        Recorder.events.append(("after_step", loop.step))

    def after_evaluation(self, loop: Any, scores: dict) -> None:
        assert "miou" in scores and loop.last_scores is scores
        Recorder.events.append(("after_evaluation", loop.step))

    def after_train(self, loop: Any) -> None:
        Recorder.events.append(("after_train", loop.step))


def test_a_registered_hook_sees_the_whole_lifecycle_and_leaves_the_identity_alone(tmp_path) -> None:
    from distilkit.registry import HOOKS

    HOOKS.add("recorder", Recorder, description="test")  # no parameters declared: it takes none
    try:
        recipe = tiny_recipe(steps=4, distill=False)
        recipe["stages"]["teacher"]["train"]["eval_every"] = 2
        plain = Pipeline(recipe_from_dict(recipe), tmp_path / "p", quiet=True).hashes
        recipe["stages"]["teacher"]["train"]["hooks"] = [{"name": "recorder"}]
        Recorder.events = []
        pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "r", quiet=True)
        assert pipe.hashes == plain  # a hook watches; it does not change what is trained
        pipe.run(stop_after=3)
        pipe.run()
    finally:
        HOOKS.remove("recorder")
    # evaluation runs in the stage's own after_step hook, before the recipe's hooks see the step
    assert Recorder.events == [("before_train", 0), ("before_step", 0), ("after_step", 1), ("before_step", 1),
                               ("after_evaluation", 2), ("after_step", 2), ("before_step", 2), ("after_step", 3),
                               ("after_train", 3),
                               ("before_train", 3), ("before_step", 3), ("after_evaluation", 4), ("after_step", 4),
                               ("after_train", 4)]  # the second run resumed from last.pt at step 3


def test_further_metrics_are_scored_beside_the_selecting_one_and_checked_by_validate(tmp_path) -> None:
    from distilkit.metrics.base import Metric
    from distilkit.registry import METRICS

    class VoxelAccuracy(Metric):
        SCORES = "voxel_logits"
        TARGETS = frozenset({"voxel_label"})
        KEYS = ("accuracy",)

        def __init__(self, info: Any) -> None:
            super().__init__(info)
            self.right, self.total = 0, 0

        def update(self, prediction: torch.Tensor, batch: Any) -> None:
            target = batch.targets["voxel_label"]
            self.right += int((prediction.argmax(1) == target).sum())
            self.total += target.numel()

        def compute(self) -> dict[str, Any]:
            return {"accuracy": self.right / max(self.total, 1)}

    METRICS.add("voxel_accuracy", VoxelAccuracy, description="test")
    try:
        recipe = tiny_recipe(steps=2, distill=False)
        recipe["stages"]["teacher"]["train"]["metrics"] = ["voxel_accuracy"]
        (teacher,) = run(tmp_path, recipe, "runs")
        scores = teacher.summary["test"]["best"]
        assert 0 < scores["voxel_accuracy.accuracy"] <= 1 and "miou" in scores
        recipe["stages"]["teacher"]["train"]["metrics"] = ["completion"]
        with pytest.raises(RecipeError, match=r"stages.teacher.train.metrics\[0\]: metric 'completion' scores points"):
            Pipeline(recipe_from_dict(recipe), tmp_path / "x", quiet=True)
    finally:
        METRICS.remove("voxel_accuracy")


def test_the_tensorboard_hook_writes_events_that_tensorboard_reads(tmp_path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    recipe = tiny_recipe(steps=4, distill=False)
    recipe["stages"]["teacher"]["train"].update(eval_every=2, log_every=1, hooks=[{"name": "tensorboard"}])
    (teacher,) = run(tmp_path, recipe, "runs")
    events = EventAccumulator(str(teacher.run_dir / "tensorboard"))
    events.Reload()
    tags = events.Tags()["scalars"]
    assert {"train/loss", "train/lr", "val/miou", "val/iou"} <= set(tags)
    logged = [json.loads(line) for line in (teacher.run_dir / "metrics.jsonl").read_text().splitlines()]
    losses = {r["step"]: r["loss"] for r in logged if "loss" in r}
    assert {e.step: e.value for e in events.Scalars("train/loss")} == pytest.approx(losses, rel=1e-6)
    assert [e.step for e in events.Scalars("val/miou")] == [2, 4]
    bad = tiny_recipe(steps=1, distill=False)
    bad["stages"]["teacher"]["train"]["hooks"] = [{"name": "tensorbord", "params": {}}]
    with pytest.raises(RecipeError, match="unknown hook 'tensorbord'; did you mean 'tensorboard'"):
        Pipeline(recipe_from_dict(bad), tmp_path / "x", quiet=True)
