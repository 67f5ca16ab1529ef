"""Mixed precision on the papers' networks: the sparse convolution under autocast (products in bf16, sums in float32,
gradients in the parameters' dtype) against float32, and one bf16 training step of each ``size: paper`` family on a
small input, its loss within 1 % of float32's (measured: 0.01 % SCPNet, 0.04 % JS3C-Net, 0.07 % LiDiff, 0.002 % its
refiner, 0.04 % VoxFormer). Before, bf16 stopped LiDiff and VoxFormer at their first step (an ``index_add_`` of bf16
products into a float32 sum)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from _camera_kitti import camera_kitti
from conftest import ROOT
from test_paper_recipes import overrides
from distilkit.sparse import SparseConvTensor, SubMConv3d

TOLERANCE = 1e-2  # relative, bf16 loss against float32's


def sites(n: int = 200, size: int = 8, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    idx = torch.unique(torch.randint(0, size, (n, 3), generator=g), dim=0)
    return torch.cat([torch.zeros(len(idx), 1, dtype=torch.long), idx], 1).int()


def test_the_sparse_convolution_under_bf16_autocast_is_float32_within_bf16_rounding() -> None:
    torch.manual_seed(0)
    idx = sites()
    feats = torch.randn(len(idx), 16, requires_grad=True)
    conv = SubMConv3d(16, 32, 3, bias=False, indice_key="a")
    ref = conv(SparseConvTensor(feats, idx, (8, 8, 8), 1)).features
    ref.square().sum().backward()
    grads = feats.grad.clone(), conv.weight.grad.clone()
    feats.grad, conv.weight.grad = None, None
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = conv(SparseConvTensor(feats, idx, (8, 8, 8), 1)).features
    assert out.dtype == torch.bfloat16  # autocast's dtype out, as the dense layers give
    assert (out.float() - ref).abs().max() <= 1e-2 * ref.abs().max()
    out.float().square().sum().backward()
    assert feats.grad.dtype == conv.weight.grad.dtype == torch.float32  # each in its own dtype
    for got, want in zip((feats.grad, conv.weight.grad), grads):
        assert (got - want).norm() <= 1e-2 * want.norm()


def test_mixed_dtypes_without_autocast_are_still_refused_naming_the_layer() -> None:
    idx = sites()
    conv = SubMConv3d(4, 4, 3, indice_key="a", name="enc.0")
    with pytest.raises(ValueError, match=r"enc\.0.*torch\.bfloat16 features against torch\.float32 weights"):
        conv(SparseConvTensor(torch.randn(len(idx), 4).bfloat16(), idx, (8, 8, 8), 1))


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return camera_kitti(tmp_path_factory)  # shared with the other paper-network modules of this process


# (paper recipe, stage): each family's network at size paper (SCPNet's and JS3C-Net's students, LiDiff's denoiser and
# refiner, the VoxFormer student on the ground truth's geometry)
FAMILIES = [("scpnet", "student_dskd"), ("js3cnet", "student_dskd"), ("scorelidar", "teacher"),
            ("scorelidar", "refiner"), ("scribble2scene", "student")]


# LiDiff's point clouds at an eighth of test_paper_recipes' small size: every level of its U-Net (5 cm voxels, strides
# to 16) still has sites, and the step's sparse convolutions scale with the points
FEWER_POINTS = {"scorelidar": ["data.params.scan_points=50", "data.params.scene_points=500"]}


def at_precision(trainer, precision: str):
    """``trainer``, its stage's ``train.precision`` set to ``precision`` (what the trainer reads at each step)."""
    import dataclasses

    spec = trainer.stage.spec
    train = spec.train.model_copy(update={"precision": precision})
    trainer.stage = dataclasses.replace(trainer.stage, spec=spec.model_copy(update={"train": train}))
    return trainer


@pytest.mark.parametrize("name, stage", FAMILIES, ids=[f"{n}-{s}" for n, s in FAMILIES])
def test_one_bf16_step_of_each_paper_network_is_float32_within_a_percent(name, stage, folder, device,
                                                                         tmp_path) -> None:
    """A bf16 trainer's first step runs (forward, backward, optimizer step) and its loss is the float32 loss of the
    same weights, batch and random draws within 1 % (float32's: the trainer's loss at fp32 before that step, which is
    the loss an fp32 step reports). SCPNet's case takes about 4 s on a 2-core CPU: two 58 M-parameter networks (the
    DSKD teacher and the student), Adam over one, at the coarsest grid the folder accepts (scale 8)."""
    from distilkit.data.probe import _one_scene
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.engine.memory.probe import probe_trainer
    from distilkit.recipe import load_recipe, parse_overrides

    path = ROOT / "recipes" / "paper" / f"{name}.yaml"
    sets = overrides(name, folder, small=True, device=device.type) + FEWER_POINTS.get(name, []) + [
        "stages.*.train.batch_size=1", f"stages.{stage}.train.precision=bf16"]
    if name == "scribble2scene":
        sets.append("stages.student.model.params.geometry=ground-truth")
    res = resolve(load_recipe(path, parse_overrides(sets)), str(path))
    assert res.stages[stage].student.cls.network(res.stages[stage].student.params).startswith("the paper's")
    trainer = probe_trainer(res, stage, _one_scene(res.data_params), tmp_path)
    assert trainer.stage.spec.train.precision == "bf16"
    batch = trainer.first_batch()
    trainer.student.train()
    cuda = device.type == "cuda"  # LiDiff draws its noise on the batch's device: CUDA's generator too
    draws = torch.get_rng_state(), torch.cuda.get_rng_state(device) if cuda else None
    with torch.no_grad():
        fp32 = float(torch.stack(list(at_precision(trainer, "fp32").loss_terms(batch).values())).sum())
    torch.set_rng_state(draws[0])  # the bf16 step draws what the float32 forward drew (LiDiff's t and noise)
    if cuda:
        torch.cuda.set_rng_state(draws[1], device)
    loss = {"fp32": fp32, "bf16": at_precision(trainer, "bf16").train_step(batch, 0)["loss"]}
    assert loss["bf16"] != loss["fp32"]  # the models did run in bf16
    assert abs(loss["bf16"] - loss["fp32"]) <= TOLERANCE * abs(loss["fp32"]), loss


def test_the_js3cnet_stand_in_trains_under_float16_autocast() -> None:
    """JS3C-Net's ``size: tiny`` pools its encoder's features into voxels with an ``index_add_`` into float32: under
    fp16 autocast (a half-precision encoder) it stopped with "self (Float) and source (Half)" (found by ``distilkit
    bench step``); now its step runs and its loss is float32's within fp16's rounding."""
    from distilkit.bench.fixtures import build, network_cases, tap_loss

    case = next(c for c in network_cases(quick=True, test=True, sizes=("tiny",)) if c.family == "JS3C-Net")
    model, batch = build(case, torch.device("cpu"))
    ref = tap_loss(model(batch))
    with torch.autocast("cpu", dtype=torch.float16):
        loss = tap_loss(model(batch))
    loss.backward()
    assert torch.isfinite(loss) and abs(float(loss) - float(ref)) <= 2e-2 * abs(float(ref)) + 1e-3
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())
