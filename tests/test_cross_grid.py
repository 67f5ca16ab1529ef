"""Sparse objectives across grids that differ by integer factors, and pairs of different adapters."""

from __future__ import annotations

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import GridMismatchError, RecipeError
from distilkit.geometry.voxel import align_across_grids, grid_factors
from distilkit.objectives.common import aligned_pairs
from distilkit.recipe import recipe_from_dict
from distilkit.taps import SparseVoxels


def _random_sparse(shape, n, c, batch=2, seed=0) -> SparseVoxels:
    g = torch.Generator().manual_seed(seed)
    x, y, z = shape
    flat = torch.randperm(batch * x * y * z, generator=g)[:n]
    coords = torch.stack(torch.unravel_index(flat, (batch, x, y, z)), 1)
    return SparseVoxels(coords, torch.randn(n, c, generator=g, dtype=torch.float64), shape)


def _naive(target_coords, target_shape, source: SparseVoxels):
    """Loop: the source voxels inside each target voxel's volume (finer) or the one containing it (coarser)."""
    out = torch.zeros(target_coords.shape[0], source.feats.shape[1], dtype=source.feats.dtype)
    found = torch.zeros(target_coords.shape[0], dtype=torch.bool)
    for i, (b, x, y, z) in enumerate(target_coords.tolist()):
        rows = []
        for j, (sb, sx, sy, sz) in enumerate(source.coords.tolist()):
            if sb != b:
                continue
            lo_t = [v / n for v, n in zip((x, y, z), target_shape)]
            hi_t = [(v + 1) / n for v, n in zip((x, y, z), target_shape)]
            lo_s = [v / n for v, n in zip((sx, sy, sz), source.spatial_shape)]
            hi_s = [(v + 1) / n for v, n in zip((sx, sy, sz), source.spatial_shape)]
            if all(max(a, c) < min(bb, d) - 1e-12 for a, bb, c, d in zip(lo_t, hi_t, lo_s, hi_s)):
                rows.append(j)
        if rows:
            out[i] = source.feats[rows].mean(0)
            found[i] = True
    return out, found


@pytest.mark.parametrize("target_shape,source_shape", [((8, 8, 4), (4, 4, 2)), ((4, 4, 2), (8, 8, 4)),
                                                       ((6, 6, 2), (6, 6, 2)), ((8, 4, 4), (4, 4, 2))])
def test_alignment_across_grids_matches_a_naive_overlap_loop(target_shape, source_shape) -> None:
    target = _random_sparse(target_shape, 40, 3, seed=1)
    source = _random_sparse(source_shape, 30, 5, seed=2)
    feats, found = align_across_grids(target.coords, target_shape, source)
    want, want_found = _naive(target.coords, target_shape, source)
    assert torch.equal(found, want_found)
    assert torch.allclose(feats, want, atol=1e-12)


def test_grids_without_an_integer_factor_are_refused_with_both_named() -> None:
    assert isinstance(grid_factors((64, 64, 8), (24, 24, 3)), str)
    assert grid_factors((64, 64, 8), (32, 32, 4)) == ("coarser", (2, 2, 2))
    s, t = _random_sparse((8, 8, 4), 10, 3), _random_sparse((6, 6, 3), 10, 3)
    with pytest.raises(GridMismatchError, match=r"\(8, 8, 4\).*\(6, 6, 3\)"):
        aligned_pairs(s, t)


def _cross(teacher: str, student: str, distill: list[dict]) -> dict:
    r = tiny_recipe(steps=1, distill=False)
    params = {"scpnet": {"channels": 4, "point_mlp": [8], "seg_channels": 4},
              "js3cnet": {"seg_channels": 4, "embed": 4, "ssc_channels": 4, "pvi_hidden": 4, "knn": 4}}
    r["stages"]["teacher"]["model"] = {"adapter": teacher, "params": {**params[teacher], "frames": 2}}
    r["stages"]["student"] = {"model": {"adapter": student, "params": {**params[student], "frames": 1}},
                              "teacher": {"from": "teacher"}, "distill": distill,
                              "train": r["stages"]["teacher"]["train"]}
    return r


@pytest.mark.parametrize("teacher,student", [("js3cnet", "scpnet"), ("scpnet", "js3cnet")])
def test_different_adapters_distil_both_ways_with_dskd_across_grids(tmp_path, teacher, student) -> None:
    distill = [{"name": "dskd", "weight": 10.0, "taps": {"student": "completion", "teacher": "completion"}},
               {"name": "pkt", "weight": 1.0, "params": {"sample_size": 64}},
               {"name": "pvkd", "weight": 1.0}, {"name": "kd", "weight": 1.0}]
    pipe = Pipeline(recipe_from_dict(_cross(teacher, student, distill)), tmp_path / "runs", quiet=True)
    results = pipe.run()
    assert [r.summary["status"] for r in results] == ["finished", "finished"]
    rec = [__import__("json").loads(x) for x in (results[1].run_dir / "metrics.jsonl").read_text().splitlines()]
    values = [r for r in rec if "kd_dskd" in r][0]
    assert values["kd_dskd"] > 0 and values["kd_pkt"] > 0 and values["kd_pvkd"] > 0


def test_validate_rejects_grids_that_cannot_be_aligned(tmp_path, monkeypatch) -> None:
    from distilkit.registry import ADAPTERS

    cls = ADAPTERS.card("js3cnet")  # what validate reads
    monkeypatch.setattr(cls, "tap_grid", classmethod(lambda c, tap, params, info: (24, 24, 3)))
    recipe = _cross("js3cnet", "scpnet", [{"name": "dskd", "taps": {"student": "completion", "teacher": "completion"}}])
    with pytest.raises(RecipeError, match=r"stages\.student\.distill\[0\].*\(32, 32, 4\).*\(24, 24, 3\)"):
        Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)


def test_a_mismatch_found_at_run_time_names_stage_objective_and_grids(tmp_path, monkeypatch) -> None:
    """An adapter whose declaration is wrong: the run ends in one line, not a traceback."""
    from distilkit.registry import ADAPTERS

    cls = ADAPTERS.get("js3cnet")
    orig = cls.forward

    def odd_grid(self, batch):
        out = orig(self, batch)
        c = out["completion"]
        out["completion"] = SparseVoxels(c.coords, c.feats, (20, 20, 3))
        return out

    monkeypatch.setattr(cls, "forward", odd_grid)
    recipe = _cross("js3cnet", "scpnet", [{"name": "dskd", "taps": {"student": "completion", "teacher": "completion"}}])
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    with pytest.raises(GridMismatchError) as err:
        pipe.run()
    msg = str(err.value)
    assert "\n" not in msg and "stage 'student'" in msg and "objective 'dskd'" in msg
    assert "(32, 32, 4)" in msg and "(20, 20, 3)" in msg


def test_grids_with_geometry_align_only_when_they_cover_one_volume() -> None:
    from distilkit.geometry.voxel import VoxelGrid

    fine = VoxelGrid.semantickitti(4)  # 64 x 64 x 8 of 0.8 m
    assert grid_factors(fine, fine.coarsen(2)) == ("coarser", (2, 2, 2))
    assert grid_factors(fine.coarsen(2), fine) == ("finer", (2, 2, 2))
    shifted = VoxelGrid((0.8, -25.6, -2.0), (32, 32, 4), 1.6)  # same shape, moved by one fine voxel
    assert grid_factors((64, 64, 8), (32, 32, 4)) == ("coarser", (2, 2, 2))  # shapes alone cannot tell
    why = grid_factors(fine, shifted)
    assert isinstance(why, str) and "origins" in why and "(0.8, -25.6, -2.0)" in why
    smaller = VoxelGrid(fine.origin, (32, 32, 4), 0.8)  # half the extent, same voxels
    why = grid_factors(fine, smaller)
    assert isinstance(why, str) and "extents" in why


def test_sparse_taps_carry_their_grid_and_a_shifted_teacher_is_refused_at_run_time() -> None:
    from distilkit.geometry.voxel import VoxelGrid

    fine = VoxelGrid.semantickitti(4)
    s = _random_sparse((64, 64, 8), 40, 3)
    t = _random_sparse((32, 32, 4), 30, 3, seed=1)
    student = SparseVoxels(s.coords, s.feats, s.spatial_shape, fine)
    good = SparseVoxels(t.coords, t.feats, t.spatial_shape, fine.coarsen(2))
    bad = SparseVoxels(t.coords, t.feats, t.spatial_shape, VoxelGrid((0.8, -25.6, -2.0), (32, 32, 4), 1.6))
    _, want, found = aligned_pairs(s, t)  # bare shapes: the same result as matching geometry
    _, got, got_found = aligned_pairs(student, good)
    assert torch.equal(got, want) and torch.equal(got_found, found)
    assert student.detach().grid == fine and student.select_batch(0).grid == fine
    with pytest.raises(GridMismatchError, match="origins"):
        aligned_pairs(student, bad)
    with pytest.raises(ValueError, match=r"grid has shape \(32, 32, 4\) but spatial_shape is \(64, 64, 8\)"):
        SparseVoxels(s.coords, s.feats, s.spatial_shape, fine.coarsen(2))


def test_validate_refuses_a_declared_grid_off_the_others_volume(tmp_path, monkeypatch) -> None:
    from distilkit.geometry.voxel import VoxelGrid
    from distilkit.registry import ADAPTERS

    cls = ADAPTERS.card("js3cnet")  # what validate reads
    monkeypatch.setattr(cls, "tap_grid", classmethod(
        lambda c, tap, params, info: VoxelGrid((1.0, -25.6, -2.0), (32, 32, 4), 1.6) if tap == "completion" else None))
    recipe = _cross("js3cnet", "scpnet", [{"name": "dskd", "taps": {"student": "completion", "teacher": "completion"}}])
    with pytest.raises(RecipeError, match=r"stages\.student\.distill\[0\].*not one volume: origins"):
        Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
