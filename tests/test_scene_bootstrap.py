"""Scenes and seeds (issue 59, item 5): the SSC metric keeps each test scene's intersections and unions (their sums
are the split's confusion), a run writes them for its best checkpoint, and the report sets a bootstrap interval over
seeds and scenes beside the t interval over seeds, saying which is wider."""

from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from rich.console import Console

from conftest import tiny_recipe
from distilkit.data.batch import Batch
from distilkit.engine.train.pipeline import Pipeline
from distilkit.recipe import recipe_from_dict
from distilkit.report import scenes
from distilkit.report.seeds import seed_rows, write_seeds_report
from test_seeds import fake


def _naive_counts(pred: np.ndarray, target: np.ndarray, invalid: np.ndarray, k: int, ignore: int):
    keep = (target != ignore) & ~invalid
    p, g = pred[keep], target[keep]
    inter = [int(((p == c) & (g == c)).sum()) for c in range(1, k)]
    union = [int(((p == c) | (g == c)).sum()) for c in range(1, k)]
    return inter, union


def test_the_metric_keeps_each_scenes_counts_and_they_sum_to_the_splits_score() -> None:
    from distilkit.data.info import DataInfo
    from distilkit.metrics.registered import SSCScore
    from distilkit.metrics.ssc import ssc_confusion, ssc_scores

    pipe = Pipeline(recipe_from_dict(tiny_recipe(steps=1, distill=False)), "/tmp/unused", quiet=True)
    info: DataInfo = pipe.resolved.data_info
    k, ignore = info.num_classes, info.classes.ignore_index
    rng = torch.Generator().manual_seed(0)
    metric, scenes_seen, joint = SSCScore(info), [], torch.zeros((k, k), dtype=torch.int64)
    for b in range(3):  # batches of two scenes
        target = torch.randint(0, k, (2, 6, 5, 4), generator=rng)
        target[target == k - 1] = ignore if b == 0 else k - 1
        invalid = torch.rand((2, 6, 5, 4), generator=rng) < 0.2
        logits = torch.randn((2, k, 6, 5, 4), generator=rng)
        joint += ssc_confusion(logits.argmax(1), target, k, invalid, ignore)
        metric.update(logits, Batch({}, {"voxel_label": target, "invalid": invalid}, {"sample_id": [f"s{b}a", f"s{b}b"]}))
        for i in range(2):
            scenes_seen.append(_naive_counts(logits[i].argmax(0).numpy(), target[i].numpy(), invalid[i].numpy(), k,
                                             ignore))
    per = metric.per_scene()
    assert per["ids"] == ["s0a", "s0b", "s1a", "s1b", "s2a", "s2b"]
    assert per["inter"].tolist() == [s[0] for s in scenes_seen] and per["union"].tolist() == [s[1] for s in scenes_seen]
    inter, union = per["inter"].sum(0), per["union"].sum(0)
    official = metric.compute()
    assert official["class_iou"] == pytest.approx([i / u if u else 0.0 for i, u in zip(inter, union)], abs=1e-12)
    assert {k: official[k] for k in ("miou", "iou", "class_iou")} == \
        {k: ssc_scores(joint)[k] for k in ("miou", "iou", "class_iou")}  # the batch-at-once confusion's scores


def test_a_run_writes_its_best_checkpoints_scene_counts_and_they_give_its_test_score(tmp_path) -> None:
    (result,) = Pipeline(recipe_from_dict(tiny_recipe(steps=2, distill=False)), tmp_path / "runs", quiet=True).run()
    counts = scenes.read(result.run_dir)
    pipe_ids = [f"test/{i:06d}" for i in range(1)]
    assert counts is not None and counts["ids"] == pipe_ids and counts["split"] == "test"
    inter, union = counts["inter"].sum(0), counts["union"].sum(0)
    miou = np.mean([i / u if u else 0.0 for i, u in zip(inter, union)])
    assert miou == pytest.approx(result.summary["test"]["best"]["miou"], abs=1e-9)
    assert "scenes" not in result.summary["test"]["best"]  # kept out of summary.json
    assert "scene" not in (result.run_dir / "metrics.jsonl").read_text()


def _rows(tmp_path, spread_scenes: float):
    """Six seeds of a baseline and two methods on 12 scenes, with their counts written as runs write them."""
    rng = np.random.default_rng(0)
    n_scenes, k = 12, 4
    union = rng.integers(50, 200, size=(n_scenes, k))
    scene_gain = rng.normal(0, spread_scenes, size=n_scenes)
    results = {}
    for s in range(6):
        results[s] = []
        for name, gain in (("none", 0.0), ("kd", 0.03), ("dist", 0.0)):
            share = np.clip(0.5 + gain + scene_gain[:, None] * (gain != 0) + rng.normal(0, 0.02, (n_scenes, k))
                            + rng.normal(0, 0.01), 0, 1)
            inter = np.floor(union * share).astype(np.int64)
            run_dir = tmp_path / f"{name}-{s}"
            run_dir.mkdir()
            np.savez_compressed(run_dir / scenes.SCENE_COUNTS, ids=np.array([f"t/{j}" for j in range(n_scenes)]),
                                inter=inter, union=union, split=np.array("test"), step=np.array(5),
                                classes=np.array(["a", "b", "c", "d"]))
            miou = float(np.mean(inter.sum(0) / union.sum(0)))
            r = fake(name, miou, 0.5, miou, objectives=() if name == "none" else (f"{name}×1",))
            results[s].append(SimpleNamespace(**vars(r), run_dir=run_dir))
    return results


def test_the_bootstrap_interval_sits_beside_the_t_interval_and_its_estimate_is_the_tables(tmp_path) -> None:
    rows = {r["stage"]: r for r in seed_rows(_rows(tmp_path, 0.05), "none")}
    for name in ("kd", "dist"):
        boot = rows[name]["boot"]
        assert boot["estimate"] == pytest.approx(rows[name]["delta_mean"], abs=1e-12)  # the official mIoU
        assert boot["ci"][0] < boot["estimate"] < boot["ci"][1] and boot["scenes"] == 12
    # kd's gain varies from scene to scene: resampling the scenes widens its interval beyond the t interval
    width = lambda ci: ci[1] - ci[0]  # noqa: E731
    assert width(rows["kd"]["boot"]["ci"]) > width(rows["kd"]["delta_ci"])
    assert "boot" not in rows["none"]


def test_a_run_without_counts_gets_no_bootstrap_and_the_report_says_which_is_wider(tmp_path) -> None:
    results = _rows(tmp_path, 0.05)
    (results[3][2].run_dir / scenes.SCENE_COUNTS).unlink()  # one seed of dist kept none
    rows = seed_rows(results, "none")
    assert [r["stage"] for r in rows if "boot" in r] == ["kd"]
    text = write_seeds_report(tmp_path, rows, "none", Console(file=io.StringIO()), stem="results").read_text()
    section = text[text.index("## Scenes and seeds"):]
    assert "The bootstrap interval is the wider for 1 of the 1 rows" in section
    assert "| kd | " in section and section.count("\n| ") == 2  # the header and kd's row
    assert scenes.read(tmp_path / "nowhere") is None
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / scenes.SCENE_COUNTS).write_bytes(b"not an npz")
    assert scenes.read(tmp_path / "bad") is None


def test_the_bootstrap_takes_each_rows_difference_to_its_own_reference(tmp_path) -> None:
    """report.compare: kd's Δ is to dist, and so is its bootstrap (the same estimate as its Δ)."""
    rows = {r["stage"]: r for r in seed_rows(_rows(tmp_path, 0.05), "none", compare={"kd": "dist"})}
    assert rows["kd"]["reference"] == "dist"
    assert rows["kd"]["boot"]["estimate"] == pytest.approx(rows["kd"]["delta_mean"], abs=1e-12)
    assert rows["dist"]["boot"]["estimate"] == pytest.approx(rows["dist"]["delta_mean"], abs=1e-12)
