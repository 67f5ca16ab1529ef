"""SCPNet at the paper's size: the release's state dict layout (spconv 1.x kernels, bare keys) loads with the same
forward, a spconv 1.x kernel converted computes the same convolution (against a naive one), the network trains."""

from __future__ import annotations

import pytest
import torch

from conftest import TINY_DATA
from distilkit.errors import DataError
from distilkit.registry import ADAPTERS
from distilkit.sparse import SparseConvTensor, SubMConv3d
from distilkit.sparse.convert import spconv1_to_spconv2, spconv2_to_spconv1


@pytest.mark.parametrize("kernel", [(1, 3, 3), (3, 1, 3), (3, 3, 3)])
def test_a_converted_spconv1_kernel_computes_the_same_convolution(kernel) -> None:
    """spconv 1.x: out[p] = sum_i in[p + i - k // 2] W1[i0, i1, i2] with W1 (k0, k1, k2, in, out)."""
    g = torch.Generator().manual_seed(0)
    coords = torch.unique(torch.cat([torch.zeros(50, 1, dtype=torch.long), torch.randint(0, 5, (50, 3), generator=g)],
                                    1), dim=0)
    feats = torch.randn(len(coords), 3, generator=g, dtype=torch.float64)
    w1 = torch.randn(*kernel, 3, 4, generator=g, dtype=torch.float64)
    where = {tuple(c.tolist()): i for i, c in enumerate(coords)}
    want = torch.zeros(len(coords), 4, dtype=torch.float64)
    for n, c in enumerate(coords.tolist()):
        for i0 in range(kernel[0]):
            for i1 in range(kernel[1]):
                for i2 in range(kernel[2]):
                    src = (c[0], c[1] + i0 - kernel[0] // 2, c[2] + i1 - kernel[1] // 2, c[3] + i2 - kernel[2] // 2)
                    if src in where:
                        want[n] += feats[where[src]] @ w1[i0, i1, i2]
    conv = SubMConv3d(3, 4, kernel, bias=False).double()
    conv.weight.data = spconv1_to_spconv2(w1)
    assert torch.allclose(conv(SparseConvTensor(feats, coords.int(), (5, 5, 5), 1)).features, want, atol=1e-12)
    assert torch.equal(spconv2_to_spconv1(conv.weight.data), w1)


@pytest.fixture(scope="module")
def paper_net() -> torch.nn.Module:
    """One SCPNet at the paper's size (58 M parameters) for the module's tests: they only read its weights or train it
    a step (each test sets its own mode)."""
    return scpnet()


def scpnet(**kw):
    from distilkit.data.params import SyntheticParams
    from distilkit.data.datasets import synthetic_info

    cls = ADAPTERS.get("scpnet")
    torch.manual_seed(0)
    return cls(cls.Params(size="paper", **kw), synthetic_info(SyntheticParams(**TINY_DATA)))


def batch():
    """One tiny synthetic scene (its 32 x 32 x 4 grid reaches every level of the U-Net, which pools by 16 x 16 x 4)."""
    from distilkit.data.params import SyntheticParams
    from distilkit.registry import DATASETS

    entry = DATASETS.entry("synthetic-lidar")
    params = SyntheticParams(**TINY_DATA)
    ds = entry.obj(params, "train")
    return entry.meta["collate"]([ds[0]])


@pytest.mark.xdist_group("scpnet_paper")  # one worker builds the shared network
def test_the_releases_state_dict_loads_with_the_same_forward_and_a_wrong_one_is_named(tmp_path, paper_net) -> None:
    """The file loads into a copy of the network whose every weight and buffer is zero first: the same forward means
    the load set them all."""
    import copy

    model = paper_net.eval()
    state = model.state_dict()
    release = {}
    for key, value in state.items():  # the release's layout: bare keys, spconv 1.x kernels
        name = key[len("net."):]
        sparse = name.startswith("cylinder_3d_spconv_seg.") and value.dim() == 5 and \
            not name.split(".")[1].startswith(("a_conv", "ch_conv", "res_"))
        release[name] = spconv2_to_spconv1(value) if sparse else value
    assert release["cylinder_3d_spconv_seg.downCntx.conv1.weight"].shape == (1, 3, 3, 32, 32)
    assert release["cylinder_3d_spconv_seg.logits.weight"].shape == (3, 3, 3, 128, 20)
    assert release["cylinder_3d_spconv_seg.a_conv3.0.weight"].shape == (32, 32, 5, 5, 5)  # dense, untouched
    assert release["cylinder_3d_generator.PPmodel.1.weight"].shape == (64, 7)
    torch.save(release, tmp_path / "scpnet.pt")
    loaded = copy.deepcopy(model)
    for value in loaded.state_dict().values():
        value.zero_()
    from distilkit.weights import load_weights

    assert load_weights(loaded, type(loaded).read_weights(str(tmp_path / "scpnet.pt")), True, "test") == []
    b = batch()
    with torch.no_grad():
        a, c = model(b), loaded(b)
    assert torch.equal(a["logits"], c["logits"]) and torch.equal(a["completion"].feats, c["completion"].feats)
    torch.save({f"module.{k}": v for k, v in release.items()}, tmp_path / "dp.pt")  # DataParallel's prefix
    # the next two files load into the model already built (each load sets or checks every key)
    assert load_weights(loaded, type(loaded).read_weights(str(tmp_path / "dp.pt")), True, "test") == []
    release["cylinder_3d_spconv_seg.resBlock2.conv1.weight"] = torch.zeros(3, 1, 3, 32, 32)
    torch.save(release, tmp_path / "bad.pt")
    with pytest.raises(DataError, match=r"resBlock2.conv1.weight \(32, 3, 1, 3, 32\) \(model: \(64, 3, 1, 3, 32\)\)"):
        load_weights(loaded, type(loaded).read_weights(str(tmp_path / "bad.pt")), True, "bad.pt")


@pytest.mark.xdist_group("scpnet_paper")
def test_the_paper_network_trains_and_keeps_its_taps_consistent(paper_net) -> None:
    model = paper_net.train()
    model.zero_grad(set_to_none=True)
    out = model(batch())
    logits, completion = out["logits"], out["completion"]
    assert logits.shape == (1, 20, 32, 32, 4)  # the batch of one on the 32 x 32 x 4 grid, 20 classes
    active = torch.zeros(logits.shape[:1] + logits.shape[2:], dtype=torch.bool)
    active[tuple(completion.coords.long().T)] = True
    assert (logits.detach().abs().sum(1)[~active] == 0).all()  # the release's dense logits: 0 outside
    logits.sum().backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing, missing[:5]
    assert model.describe(model.params).endswith("paper size")
