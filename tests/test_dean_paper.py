"""Scribble2Scene's Dean-Labeler at the paper's size: Cylinder3D's sparse U-Net (the SCPNet adapter's, without its
completion sub-network) at the Dean's input width, over the complete geometry; it builds, keeps the geometry and
trains a step of partial CE on a small grid; its inputs against a naive transcription."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
from pydantic import ValidationError

from conftest import TINY_DATA
from distilkit.registry import ADAPTERS
from distilkit_adapters.dean.cylinder import WIDTHS, dense_inputs, voxel_inputs

SCPNET_DENSE = ("a_conv", "ch_conv", "res_")  # SCPNet's completion sub-network (dense), not Cylinder3D's


def info():
    from distilkit.data.datasets import synthetic_info
    from distilkit.data.params import SyntheticParams

    return synthetic_info(SyntheticParams(**TINY_DATA))


def dean(**kw):
    cls = ADAPTERS.get("dean-labeler")
    torch.manual_seed(0)
    return cls(cls.Params(size="paper", **kw), info())


@pytest.fixture(scope="module")
def scpnet_unet() -> dict[str, torch.Size]:
    """The SCPNet adapter's paper network's Cylinder3D U-Net: its parameters' names and shapes (built on the meta
    device: nothing allocated or initialised)."""
    cls = ADAPTERS.get("scpnet")
    with torch.device("meta"):
        net = cls(cls.Params(size="paper"), info()).net.cylinder_3d_spconv_seg
    return {k: p.shape for k, p in net.named_parameters() if not k.startswith(SCPNET_DENSE)}


@pytest.mark.parametrize("features", sorted(WIDTHS))
def test_the_paper_dean_is_the_scpnet_adapters_cylinder3d_at_its_input_width(features, scpnet_unet) -> None:
    with torch.device("meta"):  # names and shapes only
        model = dean(features=features)
    mine = {k[len("net.cylinder_3d_spconv_seg."):]: p.shape for k, p in model.named_parameters()}
    assert set(mine) == set(scpnet_unet)  # the same modules: no point featuriser, no completion sub-network
    width, c = WIDTHS[features], 32
    reads_input = {"downCntx.conv1.weight", "downCntx.conv2.weight"}  # 1x3x3 and 3x1x3 on the input, no bias
    for key, shape in mine.items():
        if key in reads_input:  # (out, k0, k1, k2, in): SCPNet's reads its 32 completed channels
            assert shape[:4] == scpnet_unet[key][:4] and shape[4] == width and scpnet_unet[key][4] == c, key
        else:
            assert shape == scpnet_unet[key], key
    count = sum(p.numel() for p in model.parameters())
    assert count == sum(s.numel() for s in scpnet_unet.values()) + 2 * 9 * c * (width - c)


def test_the_inputs_against_a_naive_transcription() -> None:
    g = torch.Generator().manual_seed(0)
    occupied = torch.rand(2, 5, 4, 3, generator=g) > 0.6
    idx = occupied.nonzero()
    for features, width in WIDTHS.items():
        sparse = voxel_inputs(idx, (5, 4, 3), features)
        dense = dense_inputs(occupied, features)
        assert sparse.shape == (len(idx), width) and dense.shape == (2, width, 5, 4, 3)
        for row, (b, x, y, z) in enumerate(idx.tolist()):
            scaled = {0: -1 + 2 * x / 4, 1: -1 + 2 * y / 3, 2: -1 + 2 * z / 2}  # index -> [-1, 1], float64
            want = [1.0] + [scaled[a] for a in {"occupancy": (), "height": (2,), "position": (0, 1, 2)}[features]]
            assert sparse[row].double().tolist() == pytest.approx(want, abs=1e-6)
            assert torch.equal(dense[b, :, x, y, z], sparse[row])
        assert not dense.permute(1, 0, 2, 3, 4)[:, ~occupied].any()  # nothing outside the geometry
    # size tiny's default input is the stand-in's as it was: occupancy, then height x occupancy
    height = torch.linspace(-1.0, 1.0, 3).expand(occupied.shape)
    assert torch.equal(dense_inputs(occupied, "height"), torch.stack([occupied.float(), height * occupied], 1))
    with pytest.raises(ValueError, match="features must be one of"):
        voxel_inputs(idx, (5, 4, 3), "rgb")  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="features"):
        ADAPTERS.get("dean-labeler").Params(size="paper", features="rgb")


def test_the_paper_dean_keeps_the_geometry_and_trains_a_step_of_partial_ce() -> None:
    from distilkit.losses.ssc import partial_ce
    from distilkit.registry import DATASETS

    entry = DATASETS.entry("synthetic-lidar")
    ds = entry.obj(entry.meta["params"](**TINY_DATA), "train")
    batch = entry.meta["collate"]([ds[0], ds[1]])
    model = dean().train()
    assert type(model).network(model.params).startswith("the paper's network")
    target, scribble = batch.field("voxel_target"), batch.field("scribble")
    occupied = (target != 0) & (target != 255)
    labelled = occupied & (scribble != 0) & (scribble != 254) & (scribble != 255)
    assert labelled.any() and tuple(target.shape[1:]) == (32, 32, 4)
    taps = model(batch)
    logits, features = taps["logits"], taps["features"]
    assert logits.shape == (2, 20, 32, 32, 4) and features.shape == (2, 128, 32, 32, 4)
    assert torch.equal(logits.argmax(1) != 0, occupied)  # the geometry as given: IoU 100 %
    per_channel = features.permute(1, 0, 2, 3, 4)
    assert not per_channel[:, ~occupied].any() and per_channel[:, occupied].abs().sum() > 0
    loss = partial_ce(logits, scribble)
    assert torch.isfinite(loss) and loss > 0
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())  # reaches every one
    torch.optim.SGD(model.parameters(), lr=1e-2).step()
    with torch.no_grad():
        assert partial_ce(model(batch)["logits"], scribble) < loss  # the step lowered the scribbles' loss


def test_the_paper_dean_refuses_a_grid_its_pooling_cannot_halve() -> None:
    cls = ADAPTERS.get("dean-labeler")
    bad = SimpleNamespace(grid=SimpleNamespace(shape=(24, 32, 4)))
    problems = cls.check_data(cls.Params(size="paper"), bad)  # type: ignore[arg-type]
    assert len(problems) == 1 and problems[0][0] == "size" and "16 x 16 x 4" in problems[0][1]
    assert cls.check_data(cls.Params(size="tiny"), bad) == []  # type: ignore[arg-type]
    assert cls.check_data(cls.Params(size="paper"), SimpleNamespace(grid=SimpleNamespace(shape=(32, 32, 4)))) == []
