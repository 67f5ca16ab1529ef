"""Which variants of a sweep are one method at several weights (validation chooses among them) and which are methods
of their own: the rows are read from written run folders (summary.json, recipe.resolved.yaml), no training."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from distilkit.sweep.results import RunRecord, method_keys, sweep_rows


def _run(root: Path, variant: str, seed: int, weights: list[float], mode: str, val: float, test: float) -> RunRecord:
    """A finished run's folder as a stage writes it: the summary (val and test mIoU) and the resolved stage."""
    run_dir = root / f"{variant}-{seed}"
    run_dir.mkdir(parents=True)
    names = ["pad", "fsd"][: len(weights)]
    summary = {"stage": variant, "label": variant, "adapter": "a", "input": "camera", "seed": seed,
               "metric": {"name": "ssc", "key": "miou"}, "objectives": [f"{n}×{w:g}" for n, w in zip(names, weights)],
               "best": {"scores": {"miou": val, "iou": 0.5}, "step": 10},
               "test": {"best": {"miou": test, "iou": 0.5}, "last": {"miou": test, "iou": 0.5}, "best_step": 10},
               "report_split": "test", "steps": 10}
    stage = {"recipe": "r", "stage": variant, "hash": f"h{variant}{seed}", "label": variant, "seed": seed,
             "teacher": {"from": "teacher", "mode": mode}, "train": {"steps": 10},
             "distill": [{"name": n, "weight": w, "params": {}} for n, w in zip(names, weights)]}
    (run_dir / "summary.json").write_text(json.dumps(summary))
    (run_dir / "recipe.resolved.yaml").write_text(yaml.safe_dump(stage))
    return RunRecord(variant, seed, run_dir, summary)


def test_variants_that_differ_only_in_weights_are_one_method_and_a_teacher_mode_makes_another(tmp_path: Path) -> None:
    runs = []
    for seed in (0, 1):
        runs += [_run(tmp_path, "none", seed, [], "eval", 0.10, 0.10),
                 _run(tmp_path, "pad_low", seed, [1.0], "eval", 0.20, 0.30),
                 _run(tmp_path, "pad_high", seed, [70.0], "eval", 0.25, 0.20),
                 _run(tmp_path, "pad_train", seed, [70.0], "train", 0.15, 0.40),
                 _run(tmp_path, "pad_fsd", seed, [70.0, 4.0], "eval", 0.12, 0.12)]
    keys = method_keys(runs)
    assert keys["pad_low"] == keys["pad_high"]  # the weight is not the method
    assert len({keys["pad_high"], keys["pad_train"], keys["pad_fsd"], keys["none"]}) == 4
    rows = {r["stage"]: r for r in sweep_rows(runs, "none", ["none", "pad_low", "pad_high", "pad_train",
                                                                "pad_fsd"])[0]}
    # validation chooses pad_high over pad_low (0.25 > 0.20), though pad_low tests higher
    assert rows["pad_high"]["chosen"] and not rows["pad_low"]["chosen"] and rows["pad_high"]["alternatives"] == 2
    # the train-mode teacher has the same objectives and weights as pad_high: a method of its own, not a weight
    assert rows["pad_train"]["chosen"] and rows["pad_train"]["alternatives"] == 1


def test_runs_without_a_resolved_recipe_keep_the_summarys_grouping(tmp_path: Path) -> None:
    runs = [_run(tmp_path, "a", 0, [1.0], "eval", 0.2, 0.2), _run(tmp_path, "b", 0, [2.0], "train", 0.3, 0.3)]
    for r in runs:
        (r.run_dir / "recipe.resolved.yaml").unlink()
    assert method_keys(runs) == {}
    rows = {r["stage"]: r for r in sweep_rows(runs, None, ["a", "b"])[0]}
    assert rows["b"]["chosen"] and not rows["a"]["chosen"]  # same input and objectives: one method's weights
