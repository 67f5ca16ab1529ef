"""JS3C-Net at the paper's size: the release's module names and shapes, the voxel pooling and the point-voxel
interaction against naive float64 versions of §3.2-3.3, the U-Net's levels, training with every parameter reached."""

from __future__ import annotations

import torch

from conftest import TINY_DATA
from distilkit.registry import ADAPTERS
from distilkit_adapters.js3cnet.paper import Interaction, first_k_mean


def js3c(**kw):
    from distilkit.data.datasets import synthetic_info
    from distilkit.data.params import SyntheticParams

    cls = ADAPTERS.get("js3cnet")
    torch.manual_seed(0)
    return cls(cls.Params(size="paper", **kw), synthetic_info(SyntheticParams(**TINY_DATA)))


def batch():
    from distilkit.data.params import SyntheticParams
    from distilkit.registry import DATASETS

    entry = DATASETS.entry("synthetic-lidar")
    ds = entry.obj(SyntheticParams(**TINY_DATA), "train")
    return entry.meta["collate"]([ds[0], ds[1]])


def test_the_modules_carry_the_releases_names_and_shapes() -> None:
    state = {k[len("net."):]: tuple(v.shape) for k, v in js3c().state_dict().items()}
    unet = "seg_head.sparseModel.2"
    deepest = unet + ".2.1.2" * 6
    assert state["seg_head.sparseModel.1.weight"] == (27, 1, 1, 16)  # one input feature (use_coords: False)
    assert state[deepest + ".0.1.1.weight"] == (27, 1, 112, 112)  # 7 m at the 7th level, residual blocks
    assert deepest + ".2.1.1.weight" not in state
    assert state[unet + ".2.1.1.weight"] == (8, 1, 16, 32) and state[unet + ".2.1.4.weight"] == (8, 1, 32, 16)
    assert state[unet + ".4.0.weight"] == (32, 16)  # the NetworkInNetwork shortcut of the first tail block
    assert unet + ".0.1.0.num_batches_tracked" not in state and state[unet + ".0.1.0.running_var"] == (16,)
    assert state["seg_head.linear.weight"] == (19, 16)
    assert state["seg_head.shape_embedding.conv.weight"] == (16, 16, 1)
    assert state["seg_head.shape_embedding.bn.bn.weight"] == (16,)
    assert state["complet_head.Decoder.b1_conv1.0.weight"] == (16, 35, 7, 7, 7)  # 19 labelled classes + m = 16
    assert state["complet_head.Decoder.b4_conv1.0.weight"] == (32, 32, 3, 3, 3)
    assert state["complet_head.Decoder.pre_conv1.0.weight"] == (64, 96, 1, 1, 1)
    assert state["complet_head.Decoder.pre_conv2.0.weight"] == (20, 64, 1, 1, 1)
    assert state["complet_head.interaction_module.relation_w.conv.weight"] == (16, 10, 1)
    assert state["complet_head.interaction_module.fuse_mlps.fc.weight"] == (20, 36)
    assert state["complet_head.upsample.0.weight"] == (160, 20, 1, 1, 1)
    assert js3c(levels=5).state_dict()["net." + unet + ".2.1.2" * 4 + ".0.1.1.weight"].shape == (27, 1, 80, 80)


def test_voxel_pooling_averages_each_voxels_first_k_points_padded_with_its_first() -> None:
    g = torch.Generator().manual_seed(1)
    groups = torch.randint(0, 6, (40,), generator=g)
    values = torch.randn(40, 3, generator=g, dtype=torch.float64)
    got = first_k_mean(values, groups, 7, 3)
    for v in range(7):
        rows = [i for i in range(40) if groups[i] == v][:3]
        want = values[rows + [rows[0]] * (3 - len(rows))].mean(0) if rows else torch.zeros(3, dtype=torch.float64)
        assert torch.allclose(got[v], want, atol=1e-12)


def test_the_interaction_matches_a_naive_one_in_float64_with_gradients() -> None:
    g = torch.Generator().manual_seed(2)
    pvi = Interaction(4, 5, 3).double().eval()
    for p in pvi.parameters():
        p.data.normal_(generator=g)
    pvi.relation_w.bn.bn.running_mean.normal_(generator=g)
    q, s = torch.rand(6, 3, generator=g, dtype=torch.float64), torch.rand(9, 3, generator=g, dtype=torch.float64)
    feats = torch.randn(9, 4, generator=g, dtype=torch.float64)
    conv, bn = pvi.relation_w.conv, pvi.relation_w.bn.bn
    want = []
    for i in range(6):
        order = sorted(range(9), key=lambda j: float((s[j] - q[i]).norm()))[:3]
        acc = torch.zeros(4, dtype=torch.float64)
        for j in order:
            rel = torch.cat([s[j] - q[i], q[i], s[j], (s[j] - q[i]).norm()[None]])
            w = conv.weight[:, :, 0] @ rel
            w = (w - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps) * bn.weight + bn.bias
            acc = acc + torch.nn.functional.leaky_relu(w, 0.2) * feats[j]
        want.append(acc / 3)
    idx = torch.tensor([sorted(range(9), key=lambda j: float((s[j] - q[i]).norm()))[:3] for i in range(6)])
    assert torch.allclose(pvi.aggregate(q, s, feats, idx), torch.stack(want), atol=1e-10)
    feats.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f: pvi.aggregate(q, s, f, idx), (feats,))


def test_the_paper_network_trains_and_its_taps_fit_the_grid() -> None:
    model = js3c().train()
    out = model(batch())
    assert out["logits"].shape == (2, 20, 32, 32, 4)
    assert out["ssc_dense"].shape == (2, 64, 16, 16, 2)
    assert len(out["point_logits"]) == len(out["point_target"])
    completion = out["completion"]
    assert completion.feats.shape[1] == 64 and (completion.coords[:, 1:] < torch.tensor([16, 16, 2])).all()
    (out["logits"].sum() + out["point_logits"].sum() + completion.feats.sum()).backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing, missing[:5]
    assert model.describe(model.params).endswith("paper size")
    labelled = out["point_logits"][:, 1:]  # class 0 (never a target) 10^4 below: softmax over the 19
    assert torch.equal(torch.softmax(out["point_logits"], 1)[:, 1:], torch.softmax(labelled, 1))
    assert len(completion.coords) == int((out["ssc_dense"].abs().sum(1) > 0).sum())  # every non-zero coarse voxel
    near = js3c(pvi_queries="near").train()(batch())["completion"]
    assert len(near.coords) < len(completion.coords)
