"""Training augmentation by a finite group of flips and quarter turns (issue 58, item 3): every field of a sample
transformed alike (each target kind's round trip, against a naive per-voxel transcription), the group as JS3C-Net's
paper draws it, the draws seeded per step (a resumed run sees the same), and a stage that trains with it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from distilkit.data.augment import (Augmented, Element, affine, elements, transform_grid, transform_points,
                                    transform_sample)
from distilkit.structures import VoxelGrid

GRID = VoxelGrid((0.0, -25.6, -2.0), (16, 16, 4), 3.2)  # SemanticKITTI's volume, coarse
D4 = elements(["x", "y"], rotate90=True)


def _voxelise(points: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """A (X, Y, Z) occupancy of points, written out voxel by voxel (independent of distilkit's code)."""
    out = np.zeros(grid.shape, dtype=np.uint8)
    for x, y, z in points[:, :3]:
        i = int(np.floor((x - grid.origin[0]) / grid.voxel_size))
        j = int(np.floor((y - grid.origin[1]) / grid.voxel_size))
        k = int(np.floor((z - grid.origin[2]) / grid.voxel_size))
        out[i, j, k] = 1
    return out


def _naive_grid(array: np.ndarray, e: Element) -> np.ndarray:
    """Each voxel moved to where the transform takes its centre (float64, one voxel at a time)."""
    nx, ny = array.shape[:2]
    out = np.zeros_like(array)
    m = e.matrix.astype(np.float64)
    for i, j in itertools.product(range(nx), range(ny)):
        u, v = i - (nx - 1) / 2, j - (ny - 1) / 2
        u2, v2 = m @ np.array([u, v])
        out[int(round(u2 + (nx - 1) / 2)), int(round(v2 + (ny - 1) / 2))] = array[i, j]
    return out


def _points(n: int = 300, seed: int = 0) -> np.ndarray:
    """Points strictly inside voxels (away from faces), with an intensity column."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, GRID.shape, size=(n, 3))
    xyz = np.array(GRID.origin) + (idx + rng.uniform(0.2, 0.8, size=(n, 3))) * GRID.voxel_size
    return np.concatenate([xyz, rng.uniform(size=(n, 1))], axis=1).astype(np.float32)


def test_the_groups_are_the_distinct_transforms_with_the_identity_first() -> None:
    assert len(D4) == 8  # JS3C-Net's flips and quarter turns: the square's symmetry group, each transform once
    assert len(elements(["x", "y"])) == 4 and len(elements([], rotate90=True)) == 4 and len(elements()) == 1
    assert D4[0] == Element() and len({e.matrix.tobytes() for e in D4}) == 8
    for a, b in itertools.product(D4, D4):  # closed under composition
        assert any(np.array_equal(a.matrix @ b.matrix, c.matrix) for c in D4)
    # the paper's combinations (2 flips x 4 turns) reach each transform exactly twice: uniform over the 8
    reached = [Element(fx, fy, t).matrix.tobytes() for fx, fy, t in itertools.product((0, 1), (0, 1), range(4))]
    assert sorted(reached.count(e.matrix.tobytes()) for e in D4) == [2] * 8


@pytest.mark.parametrize("e", D4, ids=[e.name for e in D4])
def test_a_grid_moves_as_the_naive_transcription_moves_each_voxel(e: Element) -> None:
    array = np.random.default_rng(1).integers(0, 20, size=(8, 8, 3)).astype(np.uint8)
    assert np.array_equal(transform_grid(array, e), _naive_grid(array, e))


@pytest.mark.parametrize("e", D4, ids=[e.name for e in D4])
def test_points_and_their_voxels_stay_aligned(e: Element) -> None:
    """Voxelising the transformed scan is transforming the voxelised scan — at the grid's resolution and at half of
    it (VoxFormer's proposals); an inverse exists in the group and undoes it."""
    points = _points()
    moved = transform_points(points, e, GRID)
    assert np.array_equal(_voxelise(moved, GRID), transform_grid(_voxelise(points, GRID), e))
    half = VoxelGrid(GRID.origin, tuple(s // 2 for s in GRID.shape), GRID.voxel_size * 2)
    assert np.array_equal(_voxelise(moved, half), transform_grid(_voxelise(points, half), e))
    assert np.array_equal(moved[:, 2:], points[:, 2:])  # height and intensity untouched
    inverse = next(f for f in D4 if np.array_equal(f.matrix @ e.matrix, np.eye(2)))
    np.testing.assert_allclose(transform_points(moved, inverse, GRID), points, atol=1e-5)


@pytest.mark.parametrize("e", D4, ids=[e.name for e in D4])
def test_a_camera_sees_the_transformed_scene_where_it_saw_the_scene(e: Element) -> None:
    """``lidar_to_camera`` is composed with the inverse transform: every point projects to the same pixel."""
    from distilkit.data.camera import intrinsics, lidar_to_camera
    from distilkit.data.params import CameraParams

    k, t = intrinsics(CameraParams()), lidar_to_camera()
    sample = {"points": _points(), "lidar_to_camera": t[None].astype(np.float32),
              "intrinsics": k[None].astype(np.float32)}
    moved = transform_sample(sample, e, GRID)

    def pixels(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        cam = np.c_[points[:, :3].astype(np.float64), np.ones(len(points))] @ pose.T
        uvw = cam[:, :3] @ k.T
        return uvw[:, :2] / uvw[:, 2:]

    np.testing.assert_allclose(pixels(moved["points"], moved["lidar_to_camera"][0].astype(np.float64)),
                               pixels(sample["points"], t), rtol=1e-4, atol=1e-3)
    assert moved["intrinsics"] is sample["intrinsics"]
    np.testing.assert_allclose(affine(e, GRID)[:2, :2], e.matrix)


def test_every_field_of_a_street_sample_is_kept_aligned_or_refused_by_name() -> None:
    from conftest import TINY_DATA
    from distilkit.registry import DATASETS

    entry = DATASETS.entry("synthetic-lidar")
    params = entry.meta["params"].model_validate(dict(TINY_DATA))
    grid = entry.meta["info"](params).grid
    sample = entry.obj(params, "train", None)[0]
    e = D4[5]
    out = transform_sample(sample, e, grid)
    assert set(out) == set(sample)
    for key in ("voxel_label", "invalid", "scribble"):
        assert np.array_equal(out[key], _naive_grid(sample[key], e)), key
    assert np.array_equal(out["point_label"], sample["point_label"])
    occupied = transform_grid(sample["voxel_label"] > 0, e)
    hits = _voxel_of(out["points"], grid)
    inside = hits[:, 0] >= 0
    before = _voxel_of(sample["points"], grid)
    # a point's voxel after the transform is its voxel before, moved: labels read at the point agree
    assert np.array_equal(transform_grid(sample["voxel_label"], e)[tuple(hits[inside].T)],
                          sample["voxel_label"][tuple(before[inside].T)])
    assert occupied.sum() == (sample["voxel_label"] > 0).sum()
    with pytest.raises(ValueError, match="'lidar_heat'"):
        transform_sample({**sample, "lidar_heat": np.zeros(3)}, e, grid)


def _voxel_of(points: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    idx = np.floor((points[:, :3] - np.array(grid.origin)) / grid.voxel_size).astype(int)
    ok = np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)
    return np.where(ok[:, None], idx, -1)


def test_a_rotation_refuses_a_grid_that_is_not_square() -> None:
    with pytest.raises(ValueError, match="square grid"):
        transform_grid(np.zeros((8, 4, 2)), Element(turns=1))


def test_the_draws_are_a_function_of_the_seed_and_the_step_uniform_and_sharded_like_the_samples() -> None:
    from distilkit.engine.train.distributed import World
    from distilkit.engine.train.loader import BatchPlan

    plan = BatchPlan(100, 4, seed=3, group=8)
    assert plan.items(5) == BatchPlan(100, 4, seed=3, group=8).items(5)  # a resumed run draws the same
    assert [plan.elements(s) for s in range(5)] != [BatchPlan(100, 4, seed=4, group=8).elements(s) for s in range(5)]
    assert plan.indices(7) == BatchPlan(100, 4, seed=3).indices(7)  # the order does not change with augmentation
    counts = np.bincount([e for s in range(1000) for e in plan.elements(s)], minlength=8) / 4000
    assert np.all(np.abs(counts - 1 / 8) < 0.03), counts
    two = [BatchPlan(100, 4, seed=3, world=World(rank=r, size=2), group=8).items(9) for r in (0, 1)]
    assert sorted(two[0] + two[1]) == sorted(plan.items(9))
    assert BatchPlan(100, 4, seed=3).items(2) == plan.indices(2)  # no augmentation: plain indices


def test_the_augmented_split_reads_a_transformed_sample_and_the_plain_one_for_statistics() -> None:
    data = [{"points": _points(10, s), "voxel_label": np.arange(16 * 16 * 4).reshape(16, 16, 4)} for s in range(3)]
    from distilkit.data.augment import Augmentation
    from distilkit.recipe.augment import AugmentSpec

    split = Augmented(data, Augmentation(AugmentSpec(flip=["x", "y"], rotate90="z"), GRID))
    assert len(split) == 3 and split[1] is data[1]
    np.testing.assert_array_equal(split[(1, 3)]["voxel_label"], transform_grid(data[1]["voxel_label"], D4[3]))


def test_a_stage_trains_under_the_group_and_repeats_bit_for_bit(tmp_path) -> None:
    import torch

    from conftest import tiny_recipe
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict
    from distilkit.weights import load_checkpoint

    def pipeline(path, recipe):
        return Pipeline(recipe_from_dict(recipe), path / "runs", quiet=True)

    recipe = tiny_recipe(steps=3, distill=False)
    plain = pipeline(tmp_path / "plain", recipe)
    recipe["stages"]["teacher"]["train"]["augment"] = {"flip": ["x", "y"], "rotate90": "z"}
    first = pipeline(tmp_path / "a", recipe)
    assert first.hashes["teacher"] != plain.hashes["teacher"]  # augmentation is part of what is trained
    a = first.run()[0]
    b = pipeline(tmp_path / "b", recipe).run()[0]
    wa = load_checkpoint(a.run_dir / "checkpoints" / "last.pt")["student"]
    wb = load_checkpoint(b.run_dir / "checkpoints" / "last.pt")["student"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)
    c = plain.run()[0]
    wc = load_checkpoint(c.run_dir / "checkpoints" / "last.pt")["student"]
    assert any(not torch.equal(wa[k], wc[k]) for k in wa)  # the draws changed what was seen


def test_a_recipe_names_each_axis_once() -> None:
    from distilkit.errors import RecipeError
    from distilkit.recipe import recipe_from_dict

    from conftest import tiny_recipe

    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"]["teacher"]["train"]["augment"] = {"flip": ["x", "x"]}
    with pytest.raises(RecipeError, match="augment.flip"):
        recipe_from_dict(recipe)


class _Oracle:
    """A model whose logits mark the voxels its input points fall in (a flip of the scene flips its prediction)."""

    PREDICTION_TAP = "logits"

    def __call__(self, batch):
        import torch

        occupied = torch.from_numpy(_voxelise(batch.inputs["points"].numpy(), GRID)).bool()
        logits = torch.stack([(~occupied).float(), occupied.float()])[None] * 4.0
        return {"logits": logits}


class _Fixed:
    """A model whose logits ignore the input (voting averages the inverse-transformed copies of one array)."""

    PREDICTION_TAP = "logits"

    def __init__(self) -> None:
        import torch

        self.logits = torch.randn(1, 3, *GRID.shape, generator=torch.Generator().manual_seed(0))

    def __call__(self, batch):
        return {"logits": self.logits}


def _job(model):
    import torch

    from distilkit.data.lidar import collate_lidar
    from distilkit.engine.infer.predict import Prediction

    return Prediction(model, None, collate_lidar, 1, lambda s, l: None, "", [], torch.device("cpu"), "run", D4, GRID)


def _sample() -> dict:
    points = _points()
    return {"points": points, "point_frame": np.zeros(len(points), np.uint8),
            "point_label": np.zeros(len(points), np.uint8), "voxel_label": _voxelise(points, GRID),
            "invalid": np.zeros(GRID.shape, bool)}


def test_voting_gives_an_equivariant_model_its_own_prediction() -> None:
    from distilkit.engine.infer.predict import _logits, _voted

    job = _job(_Oracle())
    voted = _voted(job, _sample())
    plain = _logits(job, _sample())[0].softmax(dim=0)
    assert voted.shape == plain.shape and np.allclose(voted.numpy(), plain.numpy(), atol=1e-6)


def test_voting_averages_each_copy_mapped_back_by_its_inverse() -> None:
    from distilkit.engine.infer.predict import _voted

    model = _Fixed()
    probs = model.logits[0].softmax(dim=0).permute(1, 2, 3, 0).numpy().astype(np.float64)  # (X, Y, Z, K)
    inverses = [next(f for f in D4 if np.array_equal(f.matrix @ e.matrix, np.eye(2))) for e in D4]
    naive = sum(_naive_grid(probs, f) for f in inverses) / len(D4)
    voted = _voted(_job(model), _sample()).permute(1, 2, 3, 0).numpy()
    np.testing.assert_allclose(voted, naive, atol=1e-6)


def _spec(**kw):
    from distilkit.recipe.augment import AugmentSpec

    return AugmentSpec.model_validate(kw)


def test_continuous_draws_have_lidiffs_distributions() -> None:
    from distilkit.data.augment import continuous_affine

    turns = np.array([continuous_affine(_spec(rotate="z"), d)[:3, :3] for d in range(2000)])
    angles = np.arctan2(turns[:, 1, 0], turns[:, 0, 0])
    assert np.allclose(turns[:, 2], [0, 0, 1]) and np.allclose(np.linalg.det(turns), 1.0)
    assert np.all(np.abs(np.histogram(angles, bins=4, range=(-np.pi, np.pi))[0] / 2000 - 0.25) < 0.04)
    tilts = np.array([continuous_affine(_spec(tilt={}), d)[:3, :3] for d in range(500)])
    assert np.allclose(tilts @ tilts.transpose(0, 2, 1), np.eye(3), atol=1e-12)  # rotations
    up = np.degrees(np.arccos(np.clip(tilts[:, 2, 2], -1, 1)))
    assert 0 < up.max() <= np.degrees(np.hypot(0.18, 0.18)) + 1e-6 and np.median(up) > 1.0  # clipped, not tiny
    scales = np.array([continuous_affine(_spec(scale=[0.95, 1.05]), d)[0, 0] for d in range(500)])
    assert scales.min() >= 0.95 and scales.max() <= 1.05 and scales.std() > 0.02
    flips = {continuous_affine(_spec(scale=[1.0, 1.0], flip=["y"]), d)[1, 1] for d in range(50)}
    assert flips == {1.0, -1.0}
    spec = _spec(rotate="z", tilt={})
    assert np.array_equal(continuous_affine(spec, 7), continuous_affine(spec, 7))


def test_a_continuous_transform_moves_a_scan_and_its_scene_together_and_refuses_a_grid() -> None:
    from distilkit.data.augment import Augmentation, transform_continuous

    rng = np.random.default_rng(0)
    sample = {"scan": rng.normal(size=(50, 3)).astype(np.float32), "scene": rng.normal(size=(80, 3)).astype(np.float32),
              "scene_id": "s0"}
    aug = Augmentation(_spec(rotate="z", tilt={}, scale=[0.95, 1.05], flip=["y"]), None)
    assert aug.draws == 2 ** 32
    out = aug.apply(sample, 12345)
    a = out["scan"][:, None] - out["scene"][None]
    b = sample["scan"][:, None] - sample["scene"][None]
    ratio = np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    assert np.allclose(ratio, ratio.flat[0], rtol=1e-5) and 0.95 <= ratio.flat[0] <= 1.05  # one similarity for both
    assert out["scene_id"] == "s0"
    with pytest.raises(ValueError, match="'voxel_label'"):
        transform_continuous({"voxel_label": np.zeros((4, 4, 2))}, np.eye(4))


def test_validate_refuses_continuous_transforms_on_voxel_data_and_names_the_field() -> None:
    from conftest import tiny_recipe
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.errors import RecipeError
    from distilkit.recipe import recipe_from_dict

    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"]["teacher"]["train"]["augment"] = {"rotate": "z", "scale": [0.95, 1.05]}
    with pytest.raises(RecipeError, match=r"stages\.teacher\.train\.augment.*rotate, scale: continuous"):
        resolve(recipe_from_dict(recipe))
    recipe["stages"]["teacher"]["train"]["augment"] = {"scale": [1.1, 0.9]}
    with pytest.raises(RecipeError, match="scale"):
        recipe_from_dict(recipe)


def test_a_resumed_augmented_stage_draws_what_the_uninterrupted_one_drew(tmp_path) -> None:
    import torch

    from conftest import tiny_recipe
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict
    from distilkit.weights import load_checkpoint

    recipe = tiny_recipe(steps=4, distill=False)
    recipe["stages"]["teacher"]["train"].update(eval_every=4, augment={"flip": ["x", "y"], "rotate90": "z"})
    Pipeline(recipe_from_dict(recipe), tmp_path / "a", quiet=True).run(stop_after=2)
    resumed = Pipeline(recipe_from_dict(recipe), tmp_path / "a", quiet=True).run()[0]
    fresh = Pipeline(recipe_from_dict(recipe), tmp_path / "b", quiet=True).run()[0]
    a = load_checkpoint(resumed.run_dir / "checkpoints" / "last.pt")["student"]
    b = load_checkpoint(fresh.run_dir / "checkpoints" / "last.pt")["student"]
    assert all(torch.equal(a[k], b[k]) for k in a)
