"""Every registered objective by name and weight only, in a real (tiny) run; trainables checkpointed."""

from __future__ import annotations

import pytest
import torch

import distilkit.losses as L

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT, tiny_recipe
from distilkit.data.batch import Batch
from distilkit.weights import load_checkpoint
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.registry import OBJECTIVES


def voxel_objectives() -> list[str]:
    """The objectives an SCPNet pair on LiDAR scenes serves (point-cloud ones run in tests/test_lidiff.py)."""
    from distilkit.registry import ADAPTERS

    from conftest import TINY_DATA
    from distilkit.data.datasets import synthetic_info
    from distilkit.data.params import SyntheticParams

    kinds = set(ADAPTERS.get("scpnet").TAPS.values()) | {"feature_map", "bev_features"}  # BEV: the recipes' BEV_TAPS
    fields = synthetic_info(SyntheticParams(**TINY_DATA)).fields
    return [e.name for e in OBJECTIVES if set(e.obj.CONSUMES.values()) <= kinds and not e.obj.REQUIRES
            and all(e.obj.default_field(role, fields) in fields for role in e.obj.BATCH)]


BEV_TAPS = {"bev": {"of": "completion", "kind": "bev_features", "collapse": "max"}}  # bird's-eye maps of both models


def with_bev_taps(r: dict) -> dict:
    """A tiny recipe whose student and teacher also have a bird's-eye tap (for LiCROcc's and the voxel-to-BEV
    terms)."""
    student = r["stages"]["student"]
    student["model"]["taps"] = dict(BEV_TAPS)
    student["teacher"] = {**student["teacher"], "taps": dict(BEV_TAPS)}
    return r


def sweep_recipe() -> dict:
    r = with_bev_taps(tiny_recipe(steps=1))
    student = r["stages"].pop("student")
    for name in voxel_objectives():
        stage = {k: v for k, v in student.items() if k != "distill"}
        stage["distill"] = [{"name": name, "weight": 1.0}]
        r["stages"][f"s_{name}"] = stage
    return r


def test_every_objective_runs_by_name_and_weight(tmp_path, monkeypatch) -> None:
    """A teacher and one student per voxel objective, a step each: every stage finishes with its term logged and
    finite, and objectives' own trainables are in the student's checkpoint. (The 16 stages' run reports and the
    recipe's report, which nothing here reads, are not written: a third of the time; the reports are tested in
    tests/test_reports.py.)"""
    import distilkit.report.run

    monkeypatch.setattr(distilkit.report.run, "write_run_report", lambda run_dir: None)
    pipe = Pipeline(recipe_from_dict(sweep_recipe()), tmp_path / "runs", quiet=True)
    results = {r.name: r for r in pipe.run(report=False)}
    assert set(results) == {"teacher"} | {f"s_{n}" for n in voxel_objectives()}
    assert len(voxel_objectives()) >= 10 and {"vsd", "structural"} <= set(OBJECTIVES.names())
    for name in voxel_objectives():
        res = results[f"s_{name}"]
        assert res.summary["status"] == "finished"
        log = (res.run_dir / "metrics.jsonl").read_text()
        assert f'"kd_{name}"' in log and "NaN" not in log
    # objectives' own trainables (FitNets' regressor connector, MGD generator) are saved with the student
    for name, part, key in (("fitnets", "connectors", "proj.weight"), ("mgd", "objectives", "generator.0.weight")):
        ckpt = load_checkpoint(results[f"s_{name}"].run_dir / "checkpoints" / "last.pt")
        assert any(k.endswith(key) for k in ckpt[part])


def test_validate_rejects_taps_the_adapter_lacks(tmp_path) -> None:
    r = tiny_recipe()
    r["stages"]["student"]["model"] = {"adapter": "js3cnet", "params": {"frames": 1, "seg_channels": 4, "embed": 4,
                                                                        "ssc_channels": 4, "pvi_hidden": 4, "knn": 4}}
    r["stages"]["student"]["distill"] = [{"name": "pkt", "weight": 1.0, "taps": {"student": "logits"}}]
    with pytest.raises(RecipeError, match="is voxel_logits, but this needs sparse_features"):
        Pipeline(recipe_from_dict(r), tmp_path)


def test_objective_metadata_is_complete() -> None:
    for entry in OBJECTIVES:
        assert entry.paper and entry.description and entry.consumes
        assert {"default_weight", "equation", "shapes"} <= set(entry.meta), entry.name
        assert entry.meta["default_weight"] == entry.obj.DEFAULT_WEIGHT
        module, _, function = entry.meta["function"].rpartition(".")  # its maths as a plain function
        assert module == "distilkit.losses" and function in L.__all__ and callable(getattr(L, function)), entry.name


def test_pvkd_affinity_equals_grouped_dskd() -> None:
    from distilkit.losses import dskd
    from distilkit.objectives.relational import PVKD
    from distilkit.taps import SparseVoxels

    g = torch.Generator().manual_seed(0)
    coords = torch.stack([torch.zeros(40, dtype=torch.long), torch.randint(0, 16, (40,), generator=g),
                          torch.randint(0, 16, (40,), generator=g), torch.randint(0, 4, (40,), generator=g)], 1)
    coords = torch.unique(coords, dim=0)
    fs = torch.randn(len(coords), 3, dtype=torch.float64, generator=g)
    ft = torch.randn(len(coords), 3, dtype=torch.float64, generator=g)
    obj = PVKD(PVKD.Params(output_weight=0.0, affinity_weight=1.0, radial_bins=2, angular_bins=2, height_bins=1))
    logits = torch.zeros(1, 2, 16, 16, 4, dtype=torch.float64)
    batch = Batch({}, {"voxel_target": torch.zeros(1, 16, 16, 4, dtype=torch.long)}, {"size": 1})
    taps = {"student": SparseVoxels(coords, fs, (16, 16, 4)), "teacher": SparseVoxels(coords, ft, (16, 16, 4)),
            "student_logits": logits, "teacher_logits": logits, **obj.batch_roles(batch)}
    got = obj.compute(taps, batch)
    from distilkit.losses.pvkd import supervoxel_ids

    ids, _ = supervoxel_ids(coords, (16, 16, 4), 2, 2, 1)
    want = torch.stack([dskd(fs[ids == i], ft[ids == i]) for i in torch.unique(ids)]).mean()
    assert got.item() == pytest.approx(want.item(), rel=1e-12)
    assert len(torch.unique(ids)) > 1


def test_objectives_doc_is_in_sync() -> None:
    from conftest import ROOT
    from distilkit.schema_doc import objectives_markdown

    assert (ROOT / "docs" / "reference" / "objectives.md").read_text() == objectives_markdown() + "\n", \
        "docs/reference/objectives.md is stale: run " \
        "`distilkit list objectives --markdown > docs/reference/objectives.md`"


def test_validate_rejects_an_adapter_without_the_tap_kind(tmp_path) -> None:
    from distilkit.adapter import Adapter
    from distilkit.registry import ADAPTERS

    class LogitsOnly(Adapter):
        TAPS = {"logits": "voxel_logits"}

        def forward(self, batch):
            return {}

    ADAPTERS.add("logits-only-test", LogitsOnly, description="test adapter", override=True)
    try:
        r = tiny_recipe()
        r["stages"]["student"]["model"] = {"adapter": "logits-only-test"}
        r["stages"]["student"]["distill"] = [{"name": "nst", "weight": 1.0}]
        with pytest.raises(RecipeError, match=r"stages.student.distill\[0\]: needs a feature_map tap for the student"):
            Pipeline(recipe_from_dict(r), tmp_path)
    finally:
        ADAPTERS._entries.pop("logits-only-test", None)


@pytest.mark.parametrize("dims", [2, 3])
def test_fitnets_regressor_2d_and_3d(dims) -> None:
    from distilkit.objectives.connectors import Connector
    from distilkit.objectives.feature import FitNets

    spatial = (6, 5) if dims == 2 else (6, 5, 2)
    s, t = torch.randn(2, 3, *spatial), torch.randn(2, 7, *spatial)
    assert FitNets.DEFAULT_CONNECTOR == "linear"  # the regressor is the linear connector the trainer applies
    conv = Connector("linear", s, t).proj
    assert conv.weight.shape[:2] == (7, 3) and conv.weight.dim() == dims + 2
    want = ((conv(s) - t) ** 2).mean()
    obj = FitNets(FitNets.Params())
    assert obj(conv(s), t, Batch({}, {}, {"size": 1})).item() == pytest.approx(want.item(), rel=1e-6)


def test_connectors_project_maps_rows_and_sparse_voxels() -> None:
    from distilkit.objectives.connectors import Connector
    from distilkit.taps import SparseVoxels

    torch.manual_seed(0)
    fmap = Connector("linear", torch.zeros(2, 3, 4, 4, 2), torch.zeros(2, 5, 4, 4, 2))
    assert fmap(torch.randn(2, 3, 4, 4, 2)).shape == (2, 5, 4, 4, 2)
    x = torch.randn(2, 3, 4, 4, 2)  # a 1x1x1 convolution is the same linear map at every voxel
    w, b = fmap.proj.weight.view(5, 3), fmap.proj.bias
    assert torch.allclose(fmap(x), torch.einsum("oc,bcxyz->boxyz", w, x) + b.view(1, 5, 1, 1, 1), atol=1e-6)
    rows = Connector("linear", torch.zeros(7, 3), torch.zeros(7, 6))
    assert rows(torch.randn(7, 3)).shape == (7, 6)
    coords = torch.zeros(4, 4, dtype=torch.long)
    sparse = Connector("linear", SparseVoxels(coords, torch.zeros(4, 3), (2, 2, 2)),
                       SparseVoxels(coords, torch.zeros(4, 8), (2, 2, 2)))
    out = sparse(SparseVoxels(coords, torch.randn(4, 3), (2, 2, 2)))
    assert out.feats.shape == (4, 8) and out.coords is coords


def test_a_recipe_connector_is_trained_with_the_student(tmp_path) -> None:
    r = tiny_recipe(steps=2)
    r["stages"]["student"]["distill"] = [{"name": "pkt", "connector": "linear",
                                          "taps": {"student": "completion", "teacher": "completion"}}]
    pipe = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    _, student = pipe.run()
    ckpt = load_checkpoint(student.run_dir / "checkpoints" / "last.pt")
    weights = {k: v for k, v in ckpt["connectors"].items() if k.endswith("weight")}
    assert list(weights) == ["0.proj.weight"]
    r["stages"]["student"]["distill"][0]["connector"] = "none"
    plain = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    assert plain.hashes["student"] != pipe.hashes["student"]  # the connector is part of the identity
    assert plain.resolved.stages["student"].distill[0].connector is None
    # fitnets: its regressor is the default linear connector
    r["stages"]["student"]["distill"] = [{"name": "fitnets"}]
    assert Pipeline(recipe_from_dict(r), tmp_path / "x", quiet=True).resolved.stages["student"].distill[0].connector \
        == "linear"


def test_the_registered_connectors_project_maps_rows_and_sparse_voxels() -> None:
    from distilkit.errors import TapError
    from distilkit.objectives.connectors import Connector
    from distilkit.registry import CONNECTORS
    from distilkit.taps import SparseVoxels

    maps_s, maps_t = torch.randn(2, 3, 4, 4, 2), torch.randn(2, 5, 4, 4, 2)
    rows_s, rows_t = torch.randn(7, 3), torch.randn(7, 5)
    coords = torch.tensor([[0, 1, 1, 0], [0, 2, 3, 1]])
    sparse_s = SparseVoxels(coords, torch.randn(2, 3), (4, 4, 2))
    sparse_t = SparseVoxels(coords, torch.randn(2, 5), (4, 4, 2))
    for kind in ("linear", "conv1x1", "mlp"):
        assert Connector(kind, maps_s, maps_t)(maps_s).shape == maps_t.shape
        assert Connector(kind, rows_s, rows_t)(rows_s).shape == rows_t.shape
        assert Connector(kind, sparse_s, sparse_t)(sparse_s).feats.shape == sparse_t.feats.shape
    assert Connector("conv3", maps_s, maps_t)(maps_s).shape == maps_t.shape
    with pytest.raises(TapError, match="conv3 needs a dense feature map"):
        Connector("conv3", rows_s, rows_t)
    assert CONNECTORS.aliases_of("linear") == ["conv1x1"]
    r = tiny_recipe()
    r["stages"]["student"]["distill"] = [{"name": "dskd", "connector": "mpl"}]
    with pytest.raises(RecipeError, match=r"distill\[0\].connector: unknown connector 'mpl'; did you mean 'mlp'"):
        Pipeline(recipe_from_dict(r), "unused", quiet=True)


def test_the_choices_of_issue_26_are_stated_by_their_components() -> None:
    """Where the papers and the released code differ, each component lists the choice (docs/reference/objectives.md's
    table)."""
    from distilkit.choices import component_choices

    stated = {(name, c.topic) for _, name, c in component_choices()}
    for want in [("scpnet", "DSKD's layer"), ("scpnet", "label rectification's scan"),
                 ("js3cnet", "SSC decoder blocks"), ("js3cnet", "segmentation resolution"), ("js3cnet", "PVI refinement"),
                 ("voxformer-proposal", "stage-1 depth"), ("voxformer", "deformable sampling offsets"),
                 ("voxformer", "align_corners"), ("lidiff", "few-step sampler"), ("lidiff", "denoiser"),
                 ("lidiff", "condition dropout"), ("lidiff-refine", "refinement training input"),
                 ("vsd", "auxiliary score network"), ("distillation_dpo", "the sign"), ("partial_ce", "class weights")]:
        assert want in stated, want
    table = (ROOT / "docs" / "reference" / "objectives.md").read_text()
    assert "| objective `distillation_dpo` | the sign |" in table
