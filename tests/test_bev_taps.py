"""Issue 60's plumbing: a bird's-eye tap of any voxel tap (``taps: {bev: {of: completion, kind: bev_features,
collapse: max}}``), the height connectors, validate's checks of both, and LiCROcc's, MonoOcc's and the voxel-to-BEV
terms training a tiny student end to end."""

from __future__ import annotations

import json
import math

import pytest
import torch

from conftest import tiny_recipe
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.losses.bev import collapse_height
from distilkit.recipe import recipe_from_dict
from distilkit.structures import SparseVoxels

BEV = {"bev": {"of": "completion", "kind": "bev_features", "collapse": "max"}}


def _recipe(distill: list[dict], student_taps=BEV, teacher_taps=BEV) -> dict:
    r = tiny_recipe(steps=2)
    student = r["stages"]["student"]
    student["model"]["taps"] = dict(student_taps)
    student["teacher"] = {"from": "teacher", **({"taps": dict(teacher_taps)} if teacher_taps else {})}
    student["distill"] = distill
    return r


def test_the_round_4_terms_train_a_student_from_bird_s_eye_taps(tmp_path) -> None:
    distill = [{"name": "licrocc_kl"}, {"name": "licrocc_bev", "params": {"auto_weight": "regularised"}},
               {"name": "licrocc_affinity", "params": {"size": [4, 4]}}, {"name": "bev_from_voxels"},
               {"name": "monoocc_kl", "taps": {"student": "completion_dense", "teacher": "completion_dense"}}]
    pipe = Pipeline(recipe_from_dict(_recipe(distill)), tmp_path, quiet=True)
    terms = pipe.resolved.stages["student"].distill
    assert [t.taps["student"] for t in terms] == ["logits", "bev", "bev", "bev", "completion_dense"]
    assert terms[3].taps["teacher"] == "completion"  # the voxel-to-BEV term collapses the teacher's voxels itself
    _, student = pipe.run()
    lines = [json.loads(x) for x in (student.run_dir / "metrics.jsonl").read_text().splitlines()]
    logged = [line for line in lines if "kd_licrocc_kl" in line]
    assert len(logged) == 2
    for key in ("kd_licrocc_kl", "kd_licrocc_bev", "kd_licrocc_affinity", "kd_bev_from_voxels", "kd_monoocc_kl"):
        assert all(math.isfinite(line[key]) for line in logged), key
    assert logged[0]["kd_bev_from_voxels"] > 0 and logged[0]["kd_licrocc_bev"] > 0
    ckpt = torch.load(student.run_dir / "checkpoints" / "last.pt", weights_only=True)
    owned = [k for k in ckpt["objectives"] if k.startswith(("1.sigma", "3.adapter"))]
    assert "1.sigma" in owned and any(k.startswith("3.adapter.1.weight") for k in owned)  # trained with the student


def test_a_collapsed_tap_is_its_voxel_tap_max_over_each_column(tmp_path) -> None:
    from distilkit.data.datasets import collate_street
    from distilkit.engine.assemble.runs import build_model

    pipe = Pipeline(recipe_from_dict(_recipe([{"name": "licrocc_bev"}])), tmp_path, quiet=True)
    model = build_model(pipe.resolved.stages["student"].student, pipe.resolved.data_info)
    ds = pipe.dataset("train")
    batch = collate_street([ds[0], ds[1]])
    with torch.no_grad():
        out = model(batch)
    sparse: SparseVoxels = out["completion"]
    assert torch.equal(out["bev"], collapse_height(sparse, "max", batch=batch.size))
    assert out["bev"].shape == (batch.size, sparse.feats.shape[1], *sparse.spatial_shape[:2])
    assert model.tap_kinds["bev"] == "bev_features"


@pytest.mark.parametrize(("taps", "distill", "says"), [
    ({"bev": {"of": "nowhere", "kind": "bev_features", "collapse": "max"}}, [{"name": "licrocc_bev"}],
     "has no tap 'nowhere'"),
    ({"bev": {"of": "bev2", "kind": "bev_features", "collapse": "max"},
      "bev2": {"of": "completion", "kind": "bev_features", "collapse": "max"}}, [{"name": "licrocc_bev"}],
     "only a voxel tap"),
    ({}, [{"name": "licrocc_bev"}], "needs a bev_features tap for the student"),
])
def test_validate_names_what_is_wrong_with_a_bird_s_eye_tap(tmp_path, taps, distill, says) -> None:
    with pytest.raises(RecipeError, match=says):
        Pipeline(recipe_from_dict(_recipe(distill, student_taps=taps)), tmp_path, quiet=True)


def test_a_height_connector_makes_a_voxel_tap_serve_a_bird_s_eye_role(tmp_path) -> None:
    distill = [{"name": "licrocc_bev", "connector": "height_max", "taps": {"student": "completion"}}]
    pipe = Pipeline(recipe_from_dict(_recipe(distill, student_taps={})), tmp_path, quiet=True)
    (term,) = pipe.resolved.stages["student"].distill
    assert term.taps == {"student": "completion", "teacher": "bev"} and term.connector == "height_max"
    _, student = pipe.run()
    lines = [json.loads(x) for x in (student.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert any(math.isfinite(line.get("kd_licrocc_bev", math.nan)) for line in lines)


def test_the_height_connectors_collapse_then_project() -> None:
    from distilkit.errors import TapError
    from distilkit.objectives.connectors import Connector

    coords = torch.tensor([[0, 0, 1, 0], [0, 0, 1, 2], [1, 1, 0, 1]])
    voxels = SparseVoxels(coords, torch.randn(3, 3), (2, 2, 3))
    teacher = torch.zeros(2, 5, 2, 2)
    for how in ("max", "mean"):
        con = Connector(f"height_{how}", voxels, teacher)
        got = con(voxels)
        expected = con.proj.proj(collapse_height(voxels, how))
        assert got.shape == (2, 5, 2, 2) and torch.allclose(got, expected)
    dense = torch.randn(2, 3, 2, 2, 3)
    assert Connector("height_mean", dense, teacher)(dense).shape == (2, 5, 2, 2)
    with pytest.raises(TapError, match="collapses voxel features"):
        Connector("height_max", torch.zeros(2, 3, 2, 2), teacher)


def test_validate_checks_the_planes_of_a_bird_s_eye_pair() -> None:
    from distilkit.geometry.grids import plane_factors
    from distilkit.structures import VoxelGrid

    teacher = VoxelGrid((0.0, -25.6, -2.0), (64, 64, 8), 0.8)
    pillars = VoxelGrid((0.0, -25.6, -2.0), (32, 32, 1), 1.6)  # a BEV student: one tall cell per column
    assert plane_factors(teacher, pillars) == ("coarser", (2, 2))  # a pillar is 2 x 2 of the teacher's columns
    assert plane_factors(teacher, VoxelGrid((0.0, -25.6, -2.0), (64, 64, 32), 0.8)) == ("same", (1, 1))
    shifted = VoxelGrid((0.8, -25.6, -2.0), (64, 64, 8), 0.8)
    assert "one area" in plane_factors(teacher, shifted)
    assert "integer factor" in plane_factors(teacher, VoxelGrid((0.0, -25.6, -2.0), (48, 48, 8), 64 * 0.8 / 48))


def test_the_bev_bench_times_each_term_against_its_release_form_with_the_same_value() -> None:
    """`distilkit bench bev --quick`: a row per term, each fast form's value the release form's (float32)."""
    import contextlib
    import io

    from distilkit.bench import run_bench

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rows = {row["objective"]: row for row in run_bench(["bev"], quick=True, repeat=1)}
    assert set(rows) == {"licrocc_kl (PDD)", "licrocc_bev (CMRD)", "licrocc_affinity (BRD)",
                         "licrocc_affinity unresized", "monoocc_kl (raw, as released)", "bev_from_voxels (LWD)"}
    for name, row in rows.items():
        assert row["fast_ms"] > 0 and row["naive_ms"] > 0 and row["rel_err"] < 1e-5, (name, row)


@pytest.mark.parametrize(("adapter", "params", "tap"), [
    ("scpnet", {"channels": 4, "point_mlp": [8], "seg_channels": 4}, "completion"),
    ("scpnet", {"channels": 4, "point_mlp": [8], "seg_channels": 4}, "completion_dense"),
    ("js3cnet", {"seg_channels": 4, "embed": 4, "ssc_channels": 4, "pvi_hidden": 4, "knn": 4}, "completion"),
    ("voxformer", {"geometry": "ground-truth"}, "query_features"),
    ("voxformer", {"geometry": "ground-truth"}, "logits"),
])
def test_each_voxel_network_has_a_bird_s_eye_tap_of_its_voxel_taps(adapter, params, tap) -> None:
    """SCPNet, JS3C-Net and the VoxFormer-style camera model: a `bev` tap of any voxel tap (sparse or dense) is
    its column max, (B, C, X, Y) on the tap's grid's plane."""
    from conftest import TINY_DATA
    from distilkit.data.datasets import build_synthetic, collate_street, synthetic_info
    from distilkit.data.params import SyntheticParams
    from distilkit.engine.assemble.resolved import ResolvedModel
    from distilkit.engine.assemble.runs import build_model
    from distilkit.recipe import HookTapSpec
    from distilkit.registry import ADAPTERS
    from distilkit.taps import check_tap

    data = SyntheticParams(**TINY_DATA, camera={"height": 24, "width": 80})
    info = synthetic_info(data)
    cls = ADAPTERS.get(adapter)
    hooks = {"bev": HookTapSpec(of=tap, kind="bev_features", collapse="max")}
    torch.manual_seed(0)
    model = build_model(ResolvedModel(adapter, cls, cls.Params(**params), hooks), info).eval()
    ds = build_synthetic(data, "train")
    with torch.no_grad():
        out = model(collate_street([ds[0], ds[1]]))
    check_tap(out["bev"], "bev_features", f"{adapter}.bev")
    assert torch.equal(out["bev"], collapse_height(out[tap], "max", batch=2))
    plane = out[tap].spatial_shape[:2] if isinstance(out[tap], SparseVoxels) else tuple(out[tap].shape[2:4])
    assert out["bev"].shape[0] == 2 and tuple(out["bev"].shape[2:]) == tuple(plane)
