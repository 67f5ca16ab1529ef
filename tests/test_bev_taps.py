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
    distill = [{"name": "licrocc_kl"}, {"name": "licrocc_bev", "params": {"auto_weight": "release"}},
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
                         "licrocc_affinity unresized", "monoocc_kl (raw, as released)",
                         "monoocc_kl (softmax, default)", "monoocc_image", "bev_from_voxels (LWD)"}
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


def _labels(shape, seed):
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(1, 5, shape, generator=g)
    labels[torch.rand(shape, generator=g) < 0.7] = 0
    labels[torch.rand(shape, generator=g) < 0.1] = 255
    return labels


def test_cmrd_masks_the_cells_over_a_column_with_a_class_and_transposes_them_as_the_release() -> None:
    from distilkit.data.batch import Batch
    from distilkit.losses.licrocc import licrocc_bev
    from distilkit.registry import OBJECTIVES

    cls = OBJECTIVES.get("licrocc_bev")
    labels = _labels((2, 8, 8, 4), 0)
    labels[:, :, :4] = 0  # the left half of every plane empty: the mask is not symmetric
    g = torch.Generator().manual_seed(1)
    s, t = torch.randn(2, 3, 4, 4, generator=g), torch.randn(2, 3, 4, 4, generator=g)
    batch = Batch({}, {"voxel_target": labels}, {"size": 2})
    column = ((labels != 0) & (labels != 255)).any(dim=3)  # (2, 8, 8): a column holds a class
    mask = column.view(2, 4, 2, 4, 2).any(dim=4).any(dim=2)  # its blocks at the map's 4 x 4 cells
    plain = cls(cls.Params()).compute({"student": s, "teacher": t, "target": labels}, batch)
    assert torch.allclose(plain, licrocc_bev([s], [t], [mask]))
    flipped = cls(cls.Params(transpose_mask=True)).compute({"student": s, "teacher": t, "target": labels}, batch)
    assert torch.allclose(flipped, licrocc_bev([s], [t], [mask.transpose(1, 2)])) and not torch.allclose(flipped, plain)
    with pytest.raises(Exception, match="square"):
        cls(cls.Params(transpose_mask=True)).compute({"student": s[..., :2], "teacher": t[..., :2], "target": labels},
                                                      batch)


def test_scene_weights_and_the_release_s_automatic_weight() -> None:
    from distilkit.data.batch import Batch
    from distilkit.errors import DistilkitError
    from distilkit.losses.licrocc import licrocc_kl
    from distilkit.registry import OBJECTIVES

    cls = OBJECTIVES.get("licrocc_kl")
    labels = _labels((2, 4, 4, 2), 2)
    g = torch.Generator().manual_seed(3)
    s, t = torch.randn(2, 5, 4, 4, 2, generator=g), torch.randn(2, 5, 4, 4, 2, generator=g)
    taps = {"student": s, "teacher": t, "target": labels}
    flagged = Batch({}, {"voxel_target": labels}, {"size": 2, "scene_useful": [True, False]})
    weighted = cls(cls.Params(unuseful_weight=1e-5)).compute(taps, flagged)
    assert torch.allclose(weighted, licrocc_kl(s, t, labels, torch.tensor([1.0, 1e-5])))
    assert not torch.allclose(weighted, cls(cls.Params()).compute(taps, flagged))
    with pytest.raises(DistilkitError, match="scene_useful"):
        cls(cls.Params(unuseful_weight=1e-5)).compute(taps, Batch({}, {"voxel_target": labels}, {"size": 2}))
    auto = cls(cls.Params(auto_weight="release"))
    value = auto.compute(taps, flagged)
    assert torch.allclose(value, 0.5 * licrocc_kl(s, t, labels))  # 0.5 / sigma^2 at sigma = 1
    (grad,) = torch.autograd.grad(value, auto.sigma)
    assert float(grad) < 0  # no regulariser, as the release's class: sigma grows, the weight decays


def test_the_voxel_to_bev_weights_come_from_the_split_s_points_and_its_adapter_trains() -> None:
    from distilkit.data.batch import Batch
    from distilkit.registry import OBJECTIVES

    class Split:  # two samples: labelled voxels and points of classes 0..2
        def __len__(self):
            return 2

        def __getitem__(self, i):
            return {"voxel_label": torch.tensor([[0, 0, 1, 2]]).numpy(), "point_label": torch.tensor([0, 1, 1, 2]).numpy()}

    cls = OBJECTIVES.get("bev_from_voxels")
    term = cls(cls.Params())
    term.prepare(Split())
    shares = torch.tensor([2, 4, 2] + [0] * (term.num_classes - 3), dtype=torch.float64) / 8  # the points', not voxels'
    assert torch.allclose(term.class_weight.double(), 1 / (shares + 0.001) / 50, rtol=1e-6)
    coords = torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1], [0, 1, 1, 0], [1, 1, 0, 1]])
    voxels = SparseVoxels(coords, torch.randn(4, 6), (2, 2, 2))
    student = torch.randn(2, 3, 2, 2, requires_grad=True)
    labels = torch.randint(0, 3, (2, 2, 2, 2))
    batch = Batch({}, {"voxel_target": labels}, {"size": 2})
    taps = {"student": student, "teacher": voxels, "target": labels}
    term.setup(taps, batch)
    term.compute(taps, batch).backward()
    conv = term.adapter[1].weight
    assert conv.grad is not None and float(conv.grad.abs().sum()) > 0 and float(student.grad.abs().sum()) > 0


def test_a_collapsed_tap_keeps_the_rows_of_samples_without_voxels() -> None:
    from torch import nn

    from distilkit.data.batch import Batch
    from distilkit.engine.assemble.recorders import attach_recorders
    from distilkit.recipe import HookTapSpec

    class Net(nn.Module):
        def forward(self, batch):  # sample 1 of 2 has no voxel
            return {"voxels": SparseVoxels(torch.tensor([[0, 1, 0, 1]]), torch.ones(1, 3), (2, 2, 2))}

    net = Net()
    attach_recorders(net, {"bev": HookTapSpec(of="voxels", kind="bev_features", collapse="max")})
    out = net(Batch({}, {}, {"size": 2}))
    assert out["bev"].shape == (2, 3, 2, 2) and float(out["bev"][1].abs().sum()) == 0


def test_validate_refuses_a_height_connector_on_a_map_and_a_map_against_a_volume(tmp_path) -> None:
    on_map = [{"name": "licrocc_bev", "connector": "height_max", "taps": {"student": "bev"}}]
    with pytest.raises(RecipeError, match="height_max collapses a voxel tap"):
        Pipeline(recipe_from_dict(_recipe(on_map)), tmp_path, quiet=True)
    against = [{"name": "fitnets", "taps": {"student": "bev", "teacher": "completion_dense"}}]
    with pytest.raises(RecipeError, match="a bird's-eye map and a volume"):
        Pipeline(recipe_from_dict(_recipe(against)), tmp_path, quiet=True)


def test_validate_refuses_bird_s_eye_maps_of_two_planes_for_a_cell_by_cell_term(tmp_path) -> None:
    """A camera student's query grid is half the LiDAR teacher's: their planes tile, but CMRD compares cells."""
    from conftest import TINY_DATA

    camera_bev = {"bev": {"of": "query_features", "kind": "bev_features", "collapse": "max"}}
    train = {"steps": 1, "batch_size": 1, "device": "cpu"}
    recipe = {"schema_version": 1, "name": "planes", "seed": 0,
              "data": {"dataset": "synthetic-lidar", "params": {**TINY_DATA, "camera": {"height": 24, "width": 80}}},
              "stages": {"lidar": {"model": {"adapter": "scpnet", "params": {"channels": 4, "point_mlp": [8],
                                                                             "seg_channels": 4}}, "train": train},
                         "camera": {"model": {"adapter": "voxformer", "params": {"geometry": "ground-truth"},
                                              "taps": camera_bev},
                                    "teacher": {"from": "lidar", "taps": BEV},
                                    "distill": [{"name": "licrocc_bev"}], "train": train}}}
    with pytest.raises(RecipeError, match="compares the maps cell by cell: one plane"):
        Pipeline(recipe_from_dict(recipe), tmp_path, quiet=True)
