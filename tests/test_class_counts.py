"""Class weights come from the labels a stage trains on: a pseudo-label stage's weighted CE counts its overlay's
labels (not the dense labels another stage counted first), and partial CE never reads dense labels."""

from __future__ import annotations

import numpy as np
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.data.classes import IGNORE_INDEX, SCRIBBLE_UNLABELLED
from distilkit.engine.train.distributed import SINGLE
from distilkit.engine.train.loader import BatchPlan
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.train.stage import StageRun
from distilkit.engine.train.trainer import Trainer
from distilkit.losses.ssc import log_frequency_weights
from distilkit.recipe import recipe_from_dict


def naive_weights(samples, field: str, num_classes: int, scribbles: bool = False) -> torch.Tensor:
    """log-frequency weights from a plain count over the samples' own ``field`` (a class never seen: the largest)."""
    counts = np.zeros(num_classes, np.int64)
    for s in samples:
        v = np.asarray(s[field]).ravel().astype(np.int64)
        keep = v != IGNORE_INDEX
        if scribbles:
            keep &= (v != 0) & (v != SCRIBBLE_UNLABELLED)
        else:
            keep &= ~np.asarray(s["invalid"]).ravel().astype(bool)
        for c in v[keep]:
            counts[c] += 1
    w = log_frequency_weights(torch.from_numpy(counts).clamp_min(1))
    present = torch.from_numpy(counts > 0)
    return w.masked_fill(~present, float(w[present].max()))


def stage_trainer(pipe: Pipeline, name: str) -> Trainer:
    """The stage's trainer on the samples it trains on (its label overlay included)."""
    run = StageRun(pipe, name, pipe.run_dir(name))
    train_set = run.split("train")
    stage = pipe.resolved.stages[name]
    plan = BatchPlan(len(train_set), stage.spec.train.batch_size, 0, SINGLE)
    # the CPU whatever --device says: these tests read the class weights a trainer is built with, not a computation
    return Trainer(stage, pipe.resolved.data_info, train_set, plan, torch.device("cpu"), collate=pipe.collate), \
        train_set


def test_each_stage_weights_its_own_labels_pseudo_labels_included(tmp_path) -> None:
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["teacher"]["task_losses"] = [{"name": "weighted_ce"}]
    r["stages"]["teacher"]["publish"] = ["train"]
    r["stages"]["pseudo"] = {**r["stages"]["teacher"], "labels": {"from": "teacher"}, "publish": []}
    pipe = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    pipe.run(only=["teacher"])  # the teacher's published labels; the pseudo stage's trainer is built below
    k = pipe.resolved.data_info.num_classes
    dense, dense_set = stage_trainer(pipe, "teacher")  # counts the dense labels first, on the shared split
    pseudo, pseudo_set = stage_trainer(pipe, "pseudo")
    own = [pseudo_set[i] for i in range(len(pseudo_set))]
    assert not all(np.array_equal(s["voxel_label"], dense_set[i]["voxel_label"]) for i, s in enumerate(own))
    assert torch.allclose(dense.task[0].weight, naive_weights([dense_set[i] for i in range(len(dense_set))],
                                                              "voxel_label", k))
    assert torch.allclose(pseudo.task[0].weight, naive_weights(own, "voxel_label", k))
    assert not torch.allclose(pseudo.task[0].weight, dense.task[0].weight)


def test_partial_ce_is_unweighted_by_default_and_its_weights_count_scribbles_only(tmp_path) -> None:
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["teacher"]["task_losses"] = [{"name": "partial_ce"},
                                             {"name": "partial_ce", "params": {"class_weights": "log_frequency"}}]
    pipe = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    trainer, train_set = stage_trainer(pipe, "teacher")
    samples = [train_set[i] for i in range(len(train_set))]
    k = pipe.resolved.data_info.num_classes
    assert torch.equal(trainer.task[0].weight, torch.ones(k))
    assert torch.allclose(trainer.task[1].weight, naive_weights(samples, "scribble", k, scribbles=True))
    assert not torch.allclose(trainer.task[1].weight, naive_weights(samples, "voxel_label", k))
