"""LiDiff at the paper's size: MinkowskiEngine's kernel order converted exactly (against a naive ME convolution), the
released Lightning checkpoints' layout (names, shapes, kernel order) loading into the networks with the same
forward, and a wrong file named key by key."""

from __future__ import annotations

import pytest
import torch

from distilkit.errors import DataError
from distilkit.sparse import SparseConvTensor, SubMConv3d, SparseConv3d
from distilkit.sparse.convert import minkowski_to_spconv2, spconv2_to_minkowski
from distilkit.registry import ADAPTERS


def me_offset(k: int, size: tuple[int, int, int]) -> list[int]:
    """MinkowskiEngine's offset of kernel index k (kernel_region.hpp: axis i's index is k % k_i, then k //= k_i; odd
    kernels centred, even ones from 0)."""
    out = []
    for ks in size:
        i = k % ks
        out.append(i - ks // 2 if ks % 2 else i)
        k //= ks
    return out


def naive_me_conv(feats: torch.Tensor, coords: torch.Tensor, kernel: torch.Tensor, size, stride: int = 1):
    """ME's convolution written out: out[o] = sum_k kernel[k]^T in[o * stride + offset_k * 1] (stride 1: every site
    reads its neighbours; stride = kernel size (2): the output site o = floor(c / 2))."""
    where = {tuple(c.tolist()): i for i, c in enumerate(coords)}
    if stride == 1:
        outs = [tuple(c.tolist()) for c in coords]
    else:
        outs = sorted({(int(c[0]),) + tuple(int(v) // stride for v in c[1:].tolist()) for c in coords})
    result = torch.zeros(len(outs), kernel.shape[2], dtype=feats.dtype)
    for n, o in enumerate(outs):
        for k in range(kernel.shape[0]):
            off = me_offset(k, size)
            src = (o[0],) + tuple(o[a + 1] * stride + off[a] for a in range(3))
            if src in where:
                result[n] += feats[where[src]] @ kernel[k]
    return outs, result


@pytest.mark.parametrize("size", [(3, 3, 3), (1, 1, 1)])
def test_a_converted_minkowski_kernel_computes_the_same_submanifold_convolution(size) -> None:
    g = torch.Generator().manual_seed(0)
    coords = torch.unique(torch.cat([torch.zeros(60, 1, dtype=torch.long), torch.randint(0, 6, (60, 3), generator=g)],
                                    1), dim=0)
    feats = torch.randn(len(coords), 3, generator=g, dtype=torch.float64)
    kernel = torch.randn(size[0] * size[1] * size[2], 3, 4, generator=g, dtype=torch.float64)
    _, want = naive_me_conv(feats, coords, kernel, size)
    conv = SubMConv3d(3, 4, size, bias=False).double()
    flat = kernel[0] if size == (1, 1, 1) else kernel  # ME keeps a 1x1x1 stride-1 kernel 2-D
    conv.weight.data = minkowski_to_spconv2(flat, size)
    got = conv(SparseConvTensor(feats, coords.int(), (6, 6, 6), 1)).features
    assert torch.allclose(got, want, atol=1e-12)
    assert torch.equal(spconv2_to_minkowski(conv.weight.data), flat)
    # the layout alone (no reordering) would compute another convolution
    if size == (3, 3, 3):
        conv.weight.data = kernel.permute(2, 0, 1).reshape(4, 3, 3, 3, 3).permute(0, 2, 3, 4, 1).contiguous()
        assert not torch.allclose(conv(SparseConvTensor(feats, coords.int(), (6, 6, 6), 1)).features, want)


def test_a_converted_minkowski_strided_kernel_takes_sites_to_floor_half() -> None:
    g = torch.Generator().manual_seed(1)
    coords = torch.unique(torch.cat([torch.zeros(80, 1, dtype=torch.long), torch.randint(0, 8, (80, 3), generator=g)],
                                    1), dim=0)
    feats = torch.randn(len(coords), 2, generator=g, dtype=torch.float64)
    kernel = torch.randn(8, 2, 5, generator=g, dtype=torch.float64)
    outs, want = naive_me_conv(feats, coords, kernel, (2, 2, 2), stride=2)
    conv = SparseConv3d(2, 5, 2, stride=2, bias=False).double()
    conv.weight.data = minkowski_to_spconv2(kernel)
    out = conv(SparseConvTensor(feats, coords.int(), (8, 8, 8), 1))
    got = {tuple(i.tolist()): f for i, f in zip(out.indices, out.features)}
    assert sorted(got) == outs and all(torch.allclose(got[o], w, atol=1e-12) for o, w in zip(outs, want))


def lidiff(size: str = "paper", **kw):
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info

    cls = ADAPTERS.get(kw.pop("adapter", "lidiff"))
    torch.manual_seed(0)
    return cls(cls.Params(size=size, **kw), scenes_info(SceneParams()))


def release_layout(state: dict[str, torch.Tensor], prefixes: dict[str, str]) -> dict[str, torch.Tensor]:
    """Our paper network's weights written as the release stores them: its module names (``net.`` dropped), ``kernel``
    in MinkowskiEngine's (K, in, out) offset order, a 1x1x1 kernel 2-D."""
    out = {}
    for key, value in state.items():
        name = key[len("net."):]
        if name.endswith(".weight") and value.dim() == 5:
            out[name[: -len(".weight")] + ".kernel"] = spconv2_to_minkowski(value)
        else:
            out[name] = value
    assert all(k.startswith(tuple(prefixes)) for k in out)
    return out


@pytest.fixture(scope="module")
def diff_net() -> tuple[torch.nn.Module, dict[str, torch.Tensor]]:
    """LiDiff's denoiser at the paper's size (33 M parameters, built once for the module: the tests read it, each in
    eval mode) and its weights in the release's layout (callers copy before changing them)."""
    model = lidiff(duplicate=4).eval()
    return model, release_layout(model.state_dict(), {"partial_enc.": 0, "model.": 0})


def zeroed_copy(model: torch.nn.Module) -> torch.nn.Module:
    """``model`` with every weight and buffer zero: a file that loads into it with the same forward set them all."""
    import copy

    out = copy.deepcopy(model)
    for value in out.state_dict().values():
        value.zero_()
    return out


def scenes(b: int = 2, n: int = 48, k: int = 4):
    g = torch.Generator().manual_seed(3)
    scan = torch.randn(b, n, 3, generator=g) * torch.tensor([8.0, 8.0, 1.0])
    return scan, scan.repeat(1, k, 1) + 0.3 * torch.randn(b, n * k, 3, generator=g)


@pytest.mark.xdist_group("lidiff_paper")  # one worker builds the shared network
def test_lidiffs_diff_net_ckpt_loads_with_the_same_forward_and_a_wrong_one_is_named(tmp_path, device,
                                                                                     diff_net) -> None:
    model, release = diff_net
    model.eval()
    state = model.state_dict()
    assert any(k.startswith("net.partial_enc.stem.0.weight") for k in state) and "net.model.up1.0.net.0.weight" in state
    ckpt = {"state_dict": dict(release), "epoch": 9, "hyper_parameters": {"train": {"uncond_prob": 0.1}}}
    assert ckpt["state_dict"]["model.stage1.0.net.0.kernel"].shape == (8, 32, 32)  # ME's (K, in, out)
    assert ckpt["state_dict"]["model.up1.1.0.downsample.0.kernel"].shape == (384, 256)  # 1x1x1: (in, out)
    torch.save(ckpt, tmp_path / "diff_net.ckpt")
    loaded = zeroed_copy(model)
    from distilkit.weights import load_weights

    assert load_weights(loaded, type(loaded).read_weights(str(tmp_path / "diff_net.ckpt")), True, "test") == []
    scan, noisy = scenes()
    t = torch.tensor([10, 900])
    with torch.no_grad():
        want = model.predict_noise(noisy, t, scan)
        assert torch.equal(loaded.predict_noise(noisy, t, scan), want)
        on = loaded.to(device).predict_noise(noisy.to(device), t.to(device), scan.to(device)).cpu()  # --device
        assert torch.allclose(on, want, rtol=1e-4, atol=1e-4 * float(want.abs().max()))
    bad = dict(ckpt["state_dict"])
    bad.pop("model.last.0.weight")
    bad["model.extra.kernel"] = torch.zeros(27, 3, 3)
    bad["model.stem.0.kernel"] = torch.zeros(27, 4, 32)
    torch.save({"state_dict": bad}, tmp_path / "bad.ckpt")
    with pytest.raises(DataError) as err:  # the bad files load into a model already built (on the CPU): refused
        load_weights(model, type(model).read_weights(str(tmp_path / "bad.ckpt")), True, "bad.ckpt")
    text = str(err.value)
    assert "1 missing: net.model.last.0.weight" in text and "1 unexpected: net.model.extra.weight" in text
    assert "net.model.stem.0.weight (32, 3, 3, 3, 4) (model: (32, 3, 3, 3, 3))" in text
    # a key is named as the file spells it too (a kernel, not a weight)
    del bad["model.up1.1.0.downsample.0.kernel"]
    torch.save({"state_dict": bad}, tmp_path / "bad.ckpt")
    with pytest.raises(DataError, match=r"net\.model\.up1\.1\.0\.downsample\.0\.weight \(in the file: "
                                        r"model\.up1\.1\.0\.downsample\.0\.kernel\)"):
        load_weights(model, type(model).read_weights(str(tmp_path / "bad.ckpt")), True, "bad.ckpt")


@pytest.mark.xdist_group("lidiff_paper")
def test_a_malformed_minkowski_kernel_is_named_and_a_nan_refused(tmp_path, diff_net) -> None:
    """Each malformed kernel (a flat one, a non-cube of offsets) on the one network of the module."""
    from distilkit.weights import load_weights
    from distilkit.engine.assemble.checks import fit_problem

    model, release = diff_net

    class Spec:  # the resolved model spec validate passes
        cls = type(model)

    for shape, why in [((27 * 4 * 32,), r"\(3456,\)"), ((9, 3, 32), "9 offsets is not a cube")]:
        state = {**release, "model.stem.0.kernel": torch.zeros(shape)}
        torch.save({"state_dict": state}, tmp_path / "bad.ckpt")
        with pytest.raises(DataError, match=r"model\.stem\.0\.kernel: .*" + why):
            type(model).read_weights(str(tmp_path / "bad.ckpt"))
        assert "model.stem.0.kernel" in fit_problem(tmp_path / "bad.ckpt", Spec, None, True)
    state = {**release, "model.stage2.0.net.0.kernel": release["model.stage2.0.net.0.kernel"].clone()}
    state["model.stage2.0.net.0.kernel"][3, 1, 2] = float("nan")
    state["model.stage2.0.net.0.kernel"][0, 0, 0] = float("inf")
    torch.save({"state_dict": state}, tmp_path / "nan.ckpt")
    with pytest.raises(DataError, match=r"net\.model\.stage2\.0\.net\.0\.weight \(in the file: "
                                        r"model\.stage2\.0\.net\.0\.kernel\) holds 2 NaN or infinite values"):
        load_weights(model, type(model).read_weights(str(tmp_path / "nan.ckpt")), True, "nan.ckpt")  # built above


def test_lidiffs_refine_net_ckpt_loads_with_the_same_forward(tmp_path) -> None:
    model = lidiff(adapter="lidiff-refine").eval()
    torch.save({"state_dict": release_layout(model.state_dict(), {"model_refine.": 0})}, tmp_path / "refine_net.ckpt")
    loaded = zeroed_copy(model)
    from distilkit.weights import load_weights

    assert load_weights(loaded, type(loaded).read_weights(str(tmp_path / "refine_net.ckpt")), True, "test") == []
    scan, _ = scenes(1)
    with torch.no_grad():
        out = loaded.refine_cloud(scan[0].numpy())
        assert out.shape == (6 * 48, 3) and (abs(out.reshape(48, 6, 3) - scan[0].numpy()[:, None]) <= 1.0).all()
        assert (out == model.refine_cloud(scan[0].numpy())).all()


def test_the_paper_denoiser_is_conditioned_trains_and_samples() -> None:
    """The scan, t and each point's neighbours matter (points are not independent samples), and a training step
    reaches every parameter."""
    model = lidiff(duplicate=4, sample_steps=2).train()
    scan, noisy = scenes()
    t = torch.tensor([5, 500])
    eps = model.predict_noise(noisy, t, scan)
    assert eps.shape == noisy.shape
    eps.square().mean().backward()
    missing = [n for n, p in model.named_parameters() if p.requires_grad and p.grad is None]
    assert not missing, missing[:5]
    model.eval()  # no batch statistics: whatever changes a prediction goes through the network itself
    with torch.no_grad():
        base = model.predict_noise(noisy, t, scan)
        assert not torch.equal(base, model.predict_noise(noisy, t + 100, scan))
        assert not torch.equal(base, model.predict_noise(noisy, t, scan + 1.0))
        near = noisy.clone()
        near[:, 1] = near[:, 0] + torch.tensor([0.05, 0.0, 0.0])  # point 1 in the next 5 cm voxel of point 0's
        moved = near.clone()
        moved[:, 1, 0] += 0.05  # now two voxels away: point 0's prediction changes with its neighbour
        assert not torch.equal(model.predict_noise(near, t, scan)[:, 0], model.predict_noise(moved, t, scan)[:, 0])
        far = noisy.clone()
        far[1] += 3.0  # the other scene moves: this one's predictions stay (scenes are independent)
        assert torch.equal(base[0], model.predict_noise(far, t, scan)[0])
        assert model.sample(scan, steps=2).shape == (2, 4 * 48, 3)
