"""Point-cloud scenes as LiDiff trains on them: partial scan and dense static scene, from the synthetic streets."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from distilkit.data.params import SceneParams
from distilkit.data.scenes import (collate_scenes, farthest_point_sample, make_scene_sample, scan_crop,
                                   viewpoint_crop, voxel_first)
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


def test_one_original_point_per_map_voxel_and_the_open3d_viewpoint_grid() -> None:
    """LiDiff's map keeps one original point per voxel (the first: sparse_quantize's index), not their mean; its
    viewpoint grid is Open3D's, anchored at the scan's minimum bound less half a cell, not at the origin."""
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [1.5, 0.0, 0.0], [25.0, 0.0, 0.0]], np.float32)
    got = voxel_first(pts, 1.0)
    assert got.tolist() == pts[[0, 2, 3]].tolist()  # (0.3, 0.1, 0.1) shares the first point's voxel
    assert voxel_first(pts, 1.0, shift=np.array([0.8, 0.0, 0.0])).tolist() == pts[[0, 1, 2, 3]].tolist()  # world grid
    scan = np.array([[5.0, 5.0, 5.0], [7.0, 5.0, 5.0]], np.float32)  # min bound 5: cells [0, 10) + 5 - 5 = [0, 10)
    kept = viewpoint_crop(pts, scan, 10.0)
    assert len(kept) == 3 and 25.0 not in kept[:, 0]
    shifted = viewpoint_crop(np.array([[-0.5, 0.5, 0.5], [9.5, 0.5, 0.5], [10.5, 0.5, 0.5]], np.float32),
                             np.array([[1.0, 1.0, 1.0]], np.float32), 10.0)  # its cell: [-4, 6)^3, not [0, 10)^3
    assert shifted.tolist() == [[-0.5, 0.5, 0.5]]


def test_lidiffs_crops_are_by_3d_range() -> None:
    pts = np.array([[3.0, 0.0, 2.0], [49.0, 0.0, 12.0], [20.0, 0.0, 0.0], [20.0, 0.0, -5.0]], np.float32)
    # (3, 0, 2): 3.6 m in 3-D (kept; 3 m in the plane); (49, 0, 12): 50.4 m in 3-D (dropped; 49 m in the plane)
    assert scan_crop(pts, 3.5, 50.0, -4.0).tolist() == pts[[0, 2]].tolist()


def test_a_sample_follows_lidiffs_crops_and_sizes() -> None:
    p = SceneParams(**TINY)
    s = make_scene_sample(3, p)
    assert s["scan"].shape == (64, 3) and s["scene"].shape == (256, 3)
    r = np.linalg.norm(s["scan"], axis=1)
    assert (r > p.min_range).all() and (r < p.max_range).all() and (s["scan"][:, 2] > p.min_z).all()
    assert len(np.unique(s["scan"], axis=0)) == 64  # farthest-point samples are distinct
    assert (np.linalg.norm(s["scene"], axis=1) < p.max_range).all()
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
    got = {tuple(v.tolist()) for v in evaluation_ground_truth(world, raw, p).astype(float).round(3)}
    # z = 5 is above 4.4, (40, 0, 35) is 53 m away in 3-D, and (15, 0, 0)'s 10 m cell (the grid anchored at the
    # in-range scan's minimum bound (2, 1, 0) less 5 m) holds no scan point within 50 m
    assert got == {(1.0, 0.0, 0.0), (45.0, 1.0, 0.0), (1.02, 0.01, 0.0)}


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
