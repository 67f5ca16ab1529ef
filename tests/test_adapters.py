"""SCPNet and JS3C-Net adapters: architecture facts from the papers, taps, task losses."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import TINY_DATA
from distilkit.data.datasets import build_synthetic, synthetic_info
from distilkit.data.lidar import collate_lidar
from distilkit.data.params import SyntheticParams
from distilkit.losses.task import UncertaintyMultiTask
from distilkit.registry import ADAPTERS
from distilkit.taps import SparseVoxels, check_tap
from distilkit_adapters.js3cnet.model import pixel_shuffle_3d
from distilkit_adapters.scpnet.model import CompletionSubNetwork, MultiPathBlock

P = SyntheticParams(**TINY_DATA)


@pytest.fixture(scope="module")
def batch() -> dict:
    ds = build_synthetic(P, "train")
    return collate_lidar([ds[0], ds[1]])


def test_mpb_has_3_5_7_kernels_no_bias_no_batchnorm() -> None:
    from distilkit_adapters.scpnet.model import kernels_for_voxel

    assert kernels_for_voxel(0.2) == ((3, 5, 7), 3)  # the paper at full scale
    net = CompletionSubNetwork(4)
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv3d)]
    assert all(c.bias is None for c in convs)
    assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in net.modules())
    mpb = MultiPathBlock(4)
    assert sorted(p[0].kernel_size[0] for p in mpb.paths) == [3, 5, 7]
    assert sum(isinstance(m, MultiPathBlock) for m in net.modules()) == 3  # upper 1 + middle 2


def test_completion_keeps_sparsity() -> None:
    # no bias, no BN: a voxel farther than the receptive field from any input stays exactly zero
    net = CompletionSubNetwork(2)
    x = torch.zeros(1, 2, 40, 8, 8)
    x[0, :, 2, 4, 4] = torch.rand(2) + 0.5
    out = net(x)
    nz = out.abs().sum(1)[0].nonzero()
    assert len(nz) > 1  # completed (dilated)
    # radius: middle branch 3 + (3 + 1) * 2 ... bounded by 1 + 3 + 3 + 1 = 8 voxels along x
    assert int(nz[:, 0].max()) <= 2 + 8 and out[0, :, 12:].abs().sum() == 0


def test_scpnet_taps(batch, device) -> None:
    cls = ADAPTERS.get("scpnet")
    model = cls(cls.Params(frames=2, channels=4, point_mlp=[8], seg_channels=4), synthetic_info(P)).to(device)
    out = model(batch.to(device))
    for name, kind in cls.TAPS.items():
        check_tap(out[name], kind, name)
    assert out["logits"].shape == (2, 20, 32, 32, 4)
    sp: SparseVoxels = out["completion"]
    dense = out["completion_dense"]
    assert sp.feats.shape[0] == int((dense.abs().sum(1) > 0).sum())
    b, x, y, z = sp.coords[0].tolist()
    assert torch.equal(dense[b, :, x, y, z], sp.feats[0])


def test_teacher_sees_more_points_than_student(batch) -> None:
    cls = ADAPTERS.get("scpnet")
    info = synthetic_info(P)
    torch.manual_seed(0)
    student = cls(cls.Params(frames=1, channels=4, point_mlp=[8], seg_channels=4), info)
    torch.manual_seed(0)
    teacher = cls(cls.Params(frames=2, channels=4, point_mlp=[8], seg_channels=4), info)
    student.eval(), teacher.eval()
    with torch.no_grad():
        ns = student(batch)["completion"].coords.shape[0]
        nt = teacher(batch)["completion"].coords.shape[0]
    assert nt > ns


def roles(out: dict, batch) -> dict:
    """The uncertainty loss's roles as the trainer fills them from JS3C-Net's taps and the batch."""
    return {"student": out["logits"], "points": out["point_logits"], "point_target": out["point_target"],
            "target": batch.targets["voxel_target"]}


def test_js3cnet_taps_and_uncertainty_loss(batch, device) -> None:
    cls = ADAPTERS.get("js3cnet")
    model = cls(cls.Params(frames=1, seg_channels=4, embed=4, ssc_channels=4, pvi_hidden=4, knn=4),
                synthetic_info(P)).to(device)
    batch = batch.to(device)
    out = model(batch)
    for name, kind in cls.TAPS.items():
        check_tap(out[name], kind, name)
    assert out["logits"].shape == (2, 20, 32, 32, 4)
    assert out["point_logits"].shape[0] == out["point_target"].shape[0]
    assert out["completion"].spatial_shape == (16, 16, 2)
    loss = UncertaintyMultiTask(UncertaintyMultiTask.Params(init_log_var=0.3)).to(device)
    value = loss.compute(roles(out, batch), batch)
    # JS3C-Net eq. 2 with s = log sigma^2: 1/(2 sigma^2) L + log sigma
    tgt = out["point_target"].masked_fill(out["point_target"] == 0, 255)
    l_seg = F.cross_entropy(out["point_logits"], tgt, ignore_index=255)
    l_comp = F.cross_entropy(out["logits"], batch.targets["voxel_target"], ignore_index=255)
    sigma2 = torch.exp(torch.tensor(0.3))
    want = l_seg / (2 * sigma2) + l_comp / (2 * sigma2) + 2 * torch.log(sigma2.sqrt())
    assert value.item() == pytest.approx(want.item(), rel=1e-5)
    value.backward()
    assert loss.log_var.grad is not None and torch.isfinite(loss.log_var.grad).all()


def test_pixel_shuffle_3d_inverts_space_to_depth() -> None:
    x = torch.arange(2 * 8 * 2 * 3 * 1, dtype=torch.float32).view(1, 16, 2, 3, 1)
    y = pixel_shuffle_3d(x, 2)
    assert y.shape == (1, 2, 4, 6, 2)
    # channel c*8 + (i*4 + j*2 + k) of coarse voxel (x,y,z) lands at fine (2x+i, 2y+j, 2z+k)
    assert y[0, 1, 3, 4, 1] == x[0, 8 + 4 + 0 + 1, 1, 2, 0]


def test_js3cnet_class_weights_follow_the_paper(batch) -> None:
    """(max f / f_c)^(1/3) from the training split, checked against a naive count in float64."""
    import numpy as np

    from distilkit.data.classes import NUM_CLASSES
    from distilkit.losses.task import frequency_weights

    ds = build_synthetic(P, "train")
    loss = UncertaintyMultiTask(UncertaintyMultiTask.Params())
    loss.prepare(ds)
    counts = np.zeros(NUM_CLASSES)
    for i in range(len(ds)):
        s = ds[i]
        for v, inv in zip(s["voxel_label"].ravel(), s["invalid"].ravel()):
            if not inv and v != 255:
                counts[int(v)] += 1
    f = counts / counts.sum()
    present = counts > 0
    want = np.where(present, (f[present].max() / np.where(present, f, 1)) ** (1 / 3), 0)
    want[~present] = want[present].max()
    assert np.allclose(loss.comp_weight.numpy(), want, rtol=1e-6)
    assert loss.seg_weight[0] == 0  # unlabelled points carry no weight
    assert torch.allclose(frequency_weights(torch.tensor([8.0, 1.0, 0.0])), torch.tensor([1.0, 2.0, 2.0]))
    # the weights enter the CE terms
    cls = ADAPTERS.get("js3cnet")
    model = cls(cls.Params(frames=1, seg_channels=4, embed=4, ssc_channels=4, pvi_hidden=4, knn=4), synthetic_info(P))
    out = model(batch)
    l_comp = F.cross_entropy(out["logits"], batch.targets["voxel_target"], ignore_index=255, weight=loss.comp_weight)
    tgt = out["point_target"].masked_fill(out["point_target"] == 0, 255)
    l_seg = F.cross_entropy(out["point_logits"], tgt, ignore_index=255, weight=loss.seg_weight)
    assert loss.compute(roles(out, batch), batch).item() == pytest.approx((0.5 * l_seg + 0.5 * l_comp).item(), rel=1e-5)


def test_sigma_trains_at_ten_times_the_learning_rate_unless_the_recipe_says_otherwise(tmp_path) -> None:
    from conftest import tiny_recipe
    from distilkit.engine.train.pipeline import Pipeline
    from conftest import make_trainer
    from distilkit.recipe import recipe_from_dict

    def groups(recipe: dict) -> dict[str, float]:
        pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
        tr = make_trainer(pipe, "teacher")
        return {g["name"]: (g["lr"], len(g["params"])) for g in tr.optimizer.param_groups}

    recipe = tiny_recipe(distill=False, adapter="js3cnet")
    recipe["stages"]["teacher"]["optimizer"] = {"lr": 0.002}
    g = groups(recipe)
    assert g["task.uncertainty_multitask.log_var"] == (pytest.approx(0.02), 1)
    assert g["default"][0] == 0.002 and g["default"][1] > 10
    recipe["stages"]["teacher"]["optimizer"]["param_groups"] = [{"match": "student.net.ssc.*", "lr_scale": 0.5}]
    g = groups(recipe)
    assert "task.uncertainty_multitask.log_var" not in g and g["student.net.ssc.*"][0] == pytest.approx(0.001)


def test_scpnet_kernels_follow_the_grid_and_inactive_voxels_are_empty(batch) -> None:
    from distilkit_adapters.scpnet.model import EMPTY_LOGIT, kernels_for_voxel

    # receptive radius of the middle branch: 2 * conv radius + 2 * max MPB radius, in metres ~1.6 m
    for voxel in (0.2, 0.4, 0.8):
        paths, conv = kernels_for_voxel(voxel)
        radius_m = (2 * (conv // 2) + 2 * (max(paths) // 2)) * voxel
        assert radius_m == pytest.approx(1.6)
    cls = ADAPTERS.get("scpnet")
    model = cls(cls.Params(frames=1, channels=4, point_mlp=[8], seg_channels=4), synthetic_info(P))
    out = model(batch)
    active = torch.zeros(out["logits"].shape[:1] + out["logits"].shape[2:], dtype=torch.bool)
    active[tuple(out["completion"].coords.T)] = True
    assert 0 < active.float().mean() < 0.9
    off = out["logits"].permute(0, 2, 3, 4, 1)[~active]
    assert torch.all(off[:, 0] == EMPTY_LOGIT) and torch.all(off[:, 1:] == 0)
    out["logits"][~active.unsqueeze(1).expand_as(out["logits"])].sum().backward(retain_graph=True)
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in model.net.segmentation.parameters())
