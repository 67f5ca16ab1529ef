"""Point-cloud scenes as LiDiff trains on them: partial scan and dense static scene, from the synthetic streets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from distilkit.data.params import SceneParams
from distilkit.data.scenes import (collate_scenes, farthest_point_sample, make_scene_sample, viewpoint_crop,
                                   voxel_mean)
from distilkit.registry import DATASETS

TINY = {"num_train": 2, "num_val": 1, "num_test": 1, "scan_points": 64, "scene_points": 256, "frames": 3,
        "beams": 8, "azimuth_steps": 128}


def test_farthest_point_sampling_matches_its_definition() -> None:
    pts = np.random.default_rng(0).normal(size=(200, 3)).astype(np.float32)
    got = farthest_point_sample(pts, 20, start=5)
    want = [5]
    for _ in range(19):  # the point farthest from everything chosen so far
        d = np.min([((pts - pts[c]) ** 2).sum(1) for c in want], axis=0)
        want.append(int(np.argmax(d)))
    assert got.tolist() == want
    with pytest.raises(ValueError, match="20 points from 10"):
        farthest_point_sample(pts[:10], 20)


def test_voxel_mean_and_viewpoint_crop() -> None:
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [1.5, 0.0, 0.0], [25.0, 0.0, 0.0]], np.float32)
    got = voxel_mean(pts, 1.0)
    assert sorted(map(tuple, got.round(3))) == [(0.2, 0.1, 0.1), (1.5, 0.0, 0.0), (25.0, 0.0, 0.0)]
    kept = viewpoint_crop(pts, np.array([[5.0, 5.0, 5.0]], np.float32), 10.0)
    assert len(kept) == 3 and 25.0 not in kept[:, 0]  # the far point's 10 m cell holds no scan point


def test_a_sample_follows_lidiffs_crops_and_sizes() -> None:
    p = SceneParams(**TINY)
    s = make_scene_sample(3, p)
    assert s["scan"].shape == (64, 3) and s["scene"].shape == (256, 3)
    r = np.linalg.norm(s["scan"][:, :2], axis=1)
    assert (r > p.min_range).all() and (r < p.max_range).all() and (s["scan"][:, 2] > p.min_z).all()
    assert len(np.unique(s["scan"], axis=0)) == 64  # farthest-point samples are distinct
    assert (np.linalg.norm(s["scene"][:, :2], axis=1) < p.max_range).all()
    cells = {tuple(c) for c in np.floor(s["scan"] / p.viewpoint_voxel).astype(int)}
    assert all(tuple(c) in cells for c in np.floor(s["scene"] / p.viewpoint_voxel).astype(int))
    again = make_scene_sample(3, p)
    assert np.array_equal(again["scene"], s["scene"])  # a seed gives one sample


def test_the_evaluation_ground_truth_is_lidiffs_untiled_map_crop() -> None:
    """data_metrics.md §3.2: 3-D distance < 50 m, -4 < z < 4.4, the 10 m viewpoint cells of the raw scan, one point
    per map voxel (no tiling: every point distinct) and denser than the tiled training scene's distinct points."""
    from distilkit.data.scenes import evaluation_ground_truth

    p = SceneParams(**TINY)
    s = make_scene_sample(3, p)
    gt = s["scene_eval"]
    assert len(np.unique(gt, axis=0)) == len(gt) > len(np.unique(s["scene"], axis=0))
    assert (np.linalg.norm(gt, axis=1) < 50).all() and (gt[:, 2] > -4).all() and (gt[:, 2] < 4.4).all()
    world = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 5.0], [40.0, 0.0, 35.0], [45.0, 1.0, 0.0], [15.0, 0.0, 0.0],
                      [1.02, 0.01, 0.0]], np.float32)
    raw = np.array([[2.0, 1.0, 0.0], [42.0, 3.0, 0.0], [60.0, 0.0, 0.0]], np.float32)  # the last is out of range
    got = {tuple(v.tolist()) for v in evaluation_ground_truth(world, raw, p.model_copy(update={"gt_voxel": 0.1})).astype(float).round(3)}
    # z = 5 is above 4.4, (40, 0, 35) is 53 m away in 3-D, (15, 0, 0)'s 10 m cell holds no scan point within 50 m,
    # and the two points near (1, 0, 0) share a 0.1 m voxel (their mean is kept)
    assert got == {(1.01, 0.005, 0.0), (45.0, 1.0, 0.0)}


def test_the_registered_dataset_collates_padded_clouds_with_ids(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("DISTILKIT_CACHE", str(tmp_path))
    entry = DATASETS.entry("synthetic-scenes")
    params = entry.meta["params"](**TINY)
    ds = entry.obj(params, "train")
    batch = entry.meta["collate"]([ds[0], ds[1]])
    assert batch.inputs["scan"].shape == (2, 64, 3) and batch.targets["scene"].shape == (2, 256, 3)
    assert batch.inputs["scan_lengths"].tolist() == [64, 64] and batch.meta["scene_id"] == ["train/0", "train/1"]
    assert batch.fields == entry.meta["info"](params).fields
    assert list((tmp_path / "synthetic-scenes").glob("train-*.npz"))  # cached
    assert torch.equal(collate_scenes([entry.obj(params, "train")[1]]).targets["scene"][0], batch.targets["scene"][1])
    n = batch.targets["scene_eval_lengths"]
    assert [len(ds[i]["scene_eval"]) for i in (0, 1)] == n.tolist() and (batch.targets["scene_eval"][n.argmin(), n.min():] == 0).all()
    with pytest.raises(ValueError, match="multiple of scan_points"):
        entry.meta["params"](scan_points=100, scene_points=250)
