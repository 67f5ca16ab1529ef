"""Every registered objective reduces in float32 under mixed precision: with ``train.precision: bf16`` the models run
under autocast, their taps reach the objective in float32 (the trainer converts them outside autocast), and each
term's value is a float32 scalar within bf16's rounding of the same term at fp32 — on the same batch, the same
teacher and the same random draws (noise, timesteps). The voxel objectives on a tiny SCPNet pair, the point-cloud
ones on recipes/scorelidar.yaml's LiDiff students (VSD + structural, Distillation-DPO). This test found FitNets' regressor
(its connector, and any recipe's ``connector:``) running on the bf16 student tap outside autocast — a dtype error at
the first step; the taps are now float32 before the connector."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
import torch

from conftest import ROOT, tiny_recipe
from test_objectives import voxel_objectives, with_bev_taps
from distilkit.registry import OBJECTIVES

# relative: the models' bf16 outputs move the taps by bf16's rounding (2^-8) through a network. Measured: 0.015 % (DIST)
# to 0.97 % (PKT) for the voxel objectives, 0.013 % VSD, 0.004 % structural. Distillation-DPO's value on the first
# batch is a difference of nearly equal losses (its auxiliary copies start as the teacher: -1.7e-7 here), so for it
# the absolute 1e-6 decides and only the dtype and finiteness say something.
TOLERANCE = 2e-2

POINT_STAGES = {"vsd": "student", "structural": "student", "distillation_dpo": "dpo"}
POINT_SETS = ["data.params.num_train=1", "data.params.num_val=1", "data.params.num_test=1",
              "data.params.scan_points=128", "data.params.scene_points=1280", "stages.*.train.batch_size=1"]


def terms_at(res, stage: str, params, precision: str) -> dict[str, torch.Tensor]:
    """Each term's value on the stage's first batch at ``precision`` (the same seeds either way)."""
    from distilkit.engine.memory.probe import probe_trainer

    spec = res.stages[stage].spec
    res.stages[stage].spec = spec.model_copy(update={"train": spec.train.model_copy(update={"precision": precision})})
    with tempfile.TemporaryDirectory() as scratch:  # the probe's run folder, removed after
        trainer = probe_trainer(res, stage, params, Path(scratch))
        batch = trainer.first_batch()
        trainer.student.train()
        torch.manual_seed(1)
        return {k: v.detach() for k, v in trainer.loss_terms(batch).items()}


def check(terms: dict[str, dict[str, torch.Tensor]], name: str) -> None:
    keys = [k for k in terms["bf16"] if name in k]
    assert keys, (name, list(terms["bf16"]))
    for key in keys:
        low, ref = terms["bf16"][key], terms["fp32"][key]
        assert low.dtype == torch.float32 and low.dim() == 0 and torch.isfinite(low), (key, low)
        assert abs(float(low) - float(ref)) <= TOLERANCE * abs(float(ref)) + 1e-6, (key, float(low), float(ref))


CAMERA = {"monoocc_image"}  # reads image features only: checked on its own below


def test_every_registered_objective_is_covered_here() -> None:
    assert set(voxel_objectives()) | set(POINT_STAGES) | CAMERA == set(OBJECTIVES.names())


def test_the_image_objective_reduces_bf16_taps_in_float32() -> None:
    """MonoOcc's image term on image features as a bf16 camera model returns them, after the trainer's conversion
    (``to_float32``): a float32 scalar within bf16's rounding of the same term on the float32 features."""
    from distilkit.data.batch import Batch
    from distilkit.taps import to_float32

    term = OBJECTIVES.get("monoocc_image")(OBJECTIVES.get("monoocc_image").Params())
    g = torch.Generator().manual_seed(0)
    s, t = torch.randn(2, 8, 6, 20, generator=g), torch.randn(2, 8, 3, 10, generator=g)
    ref = term(s, t, Batch({}, {}, {"size": 2}))
    low = term(to_float32(s.bfloat16()), to_float32(t.bfloat16()), Batch({}, {}, {"size": 2}))
    assert low.dtype == torch.float32 and low.dim() == 0 and torch.isfinite(low)
    assert abs(float(low) - float(ref)) <= TOLERANCE * abs(float(ref)) and float(low) != float(ref)


@pytest.fixture(scope="module")
def voxel_terms() -> dict[str, dict[str, torch.Tensor]]:
    """Every voxel objective's term on one student stage that distils with all of them (weight 1 each), at fp32 and
    at bf16: one trainer per precision instead of one per objective and precision (a third of the time)."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    r = with_bev_taps(tiny_recipe(steps=1))
    r["stages"]["student"]["distill"] = [{"name": name, "weight": 1.0} for name in voxel_objectives()]
    res = resolve(recipe_from_dict(r), "objectives")
    return {p: terms_at(res, "student", res.data_params, p) for p in ("fp32", "bf16")}


@pytest.mark.xdist_group("objectives_float32")  # one worker builds the two trainers once
@pytest.mark.parametrize("name", voxel_objectives())
def test_a_voxel_objective_reduces_in_float32_under_bf16(name, voxel_terms) -> None:
    check(voxel_terms, name)  # its term kd_<name> (and, for "kd", every other kd_* term too)


@pytest.fixture(scope="module")
def point_terms() -> dict[tuple[str, str], dict[str, dict[str, torch.Tensor]]]:
    """recipes/scorelidar.yaml's terms per (stage, device), at fp32 and at bf16, each stage's computed once (VSD and
    the structural loss are terms of one stage)."""
    return {}


@pytest.mark.xdist_group("objectives_float32")
@pytest.mark.parametrize("name", sorted(POINT_STAGES))
def test_a_point_cloud_objective_reduces_in_float32_under_bf16(name, device, point_terms) -> None:
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import load_recipe, parse_overrides

    key = (POINT_STAGES[name], device.type)
    if key not in point_terms:
        path = ROOT / "recipes" / "scorelidar.yaml"
        sets = POINT_SETS + [f"stages.*.train.device={device.type}"]  # autocast on the device of --device
        res = resolve(load_recipe(path, parse_overrides(sets)), str(path))
        point_terms[key] = {p: terms_at(res, key[0], res.data_params, p) for p in ("fp32", "bf16")}
    check(point_terms[key], name)
