"""distilkit.sparse's two meanings of an existing ``indice_key``: spconv 1.x's reuse (against a naive float64 reference
of its rule, dictionary lookups over the active sites, values and gradients), spconv 2.x's errors and copies; the
checks of a tensor's indices; keywords; a layer named in a dtype error."""

from __future__ import annotations

from itertools import product

import pytest
import torch

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d, name_modules

SHAPE = (6, 7, 5)


@pytest.fixture(params=["loop", "table"])
def form(request: pytest.FixtureRequest):
    """The torch path's two forms: spconv 1.x's reuse holds in both."""
    from distilkit.sparse.form import using_form

    with using_form(request.param):
        yield request.param


def cloud(seed: int = 0, n: int = 45, channels: int = 3) -> SparseConvTensor:
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(2):
        coords = torch.unique(torch.stack([torch.randint(0, s, (n,), generator=g) for s in SHAPE], 1), dim=0)
        rows.append(torch.cat([torch.full((len(coords), 1), b), coords], 1))
    idx = torch.cat(rows).int()
    return SparseConvTensor(torch.randn(len(idx), channels, generator=g, dtype=torch.float64), idx, SHAPE, 2)


def naive_subm(feats: torch.Tensor, coords: list[tuple[int, ...]], weight: torch.Tensor,
               stored: tuple[int, int, int]) -> torch.Tensor:
    """spconv 1.x's rule: the stored map's offsets (kernel ``stored``, C order, about its centre) multiply this
    kernel's (out, k0, k1, k2, in) slices flattened in C order, one by one; a dictionary lookup per neighbour."""
    flat = weight.permute(1, 2, 3, 4, 0).reshape(-1, weight.shape[4], weight.shape[0])  # (K, in, out)
    where = {c: i for i, c in enumerate(coords)}
    offsets = list(product(*(range(k) for k in stored)))
    rows = []
    for c in coords:
        acc = feats.new_zeros(weight.shape[0])
        for i, off in enumerate(offsets):
            src = (c[0],) + tuple(c[1 + a] + off[a] - stored[a] // 2 for a in range(3))
            if src in where:
                acc = acc + feats[where[src]] @ flat[i]
        rows.append(acc)
    return torch.stack(rows)


def test_spconv1_reuses_the_first_map_whatever_the_kernel_values_and_gradients(form) -> None:
    """Cylinder3D's blocks as SCPNet's release runs them: 1x3x3 first, then 3x1x3 and 3x3x3 on its map, and a branch
    from the block's input on the shared map; a second key first used with 3x1x1 (the ReconBlock)."""
    x = cloud()
    x.features.requires_grad_()
    a = SubMConv3d(3, 4, (1, 3, 3), indice_key="bef", semantics="spconv1").double()
    b = SubMConv3d(4, 4, (3, 1, 3), indice_key="bef", semantics="spconv1").double()
    c = SubMConv3d(4, 2, (3, 3, 3), indice_key="bef", semantics="spconv1").double()
    d = SubMConv3d(3, 2, (3, 1, 3), indice_key="bef", semantics="spconv1").double()  # a branch from the input
    e = SubMConv3d(2, 2, (3, 1, 1), indice_key="recon", semantics="spconv1").double()
    f = SubMConv3d(2, 2, (1, 1, 3), indice_key="recon", semantics="spconv1").double()
    ya = a(x)
    yb = b(ya.replace_feature(torch.tanh(ya.features)))
    yc = c(yb)
    yd = d(x)
    s = yc.replace_feature(yc.features + yd.features)
    out = f(e(s))
    assert out.indice_dict is x.indice_dict and set(x.indice_dict) == {"bef", "recon"}  # one shared dictionary

    coords = [tuple(r) for r in x.indices.tolist()]
    leaf = x.features.detach().clone().requires_grad_()
    w = {m: m.weight.detach().clone().requires_grad_() for m in (a, b, c, d, e, f)}

    def conv(m, h, stored):
        return naive_subm(h, coords, w[m], stored) + m.bias.detach()

    ra = conv(a, leaf, (1, 3, 3))
    rb = conv(b, torch.tanh(ra), (1, 3, 3))
    rc = conv(c, rb, (1, 3, 3))  # the 3x3x3 kernel's slice [:, 0] at 1x3x3 offsets
    rd = conv(d, leaf, (1, 3, 3))
    ref = conv(f, conv(e, rc + rd, (3, 1, 1)), (3, 1, 1))
    assert torch.allclose(out.features, ref, rtol=1e-12, atol=1e-12)
    r = torch.randn(out.features.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (out.features * r).sum().backward()
    (ref * r).sum().backward()
    assert torch.allclose(x.features.grad, leaf.grad, rtol=1e-11, atol=1e-12)
    for m, ref_w in w.items():
        assert torch.allclose(m.weight.grad, ref_w.grad, rtol=1e-11, atol=1e-12)
    assert not c.weight.grad[:, 1:].any() and c.weight.grad[:, 0].any()  # only slice [:, 0] is read


def test_spconv1_on_its_own_map_is_the_convolution_and_a_kernel_smaller_than_the_map_is_refused(form) -> None:
    x = cloud(1)
    big = SubMConv3d(3, 3, (3, 3, 3), bias=False, indice_key="k", semantics="spconv1").double()
    small = SubMConv3d(3, 3, (1, 3, 3), bias=False, indice_key="k", semantics="spconv1").double()
    y = big(x)
    coords = [tuple(r) for r in x.indices.tolist()]
    assert torch.allclose(y.features, naive_subm(x.features, coords, big.weight.detach(), (3, 3, 3)), atol=1e-12)
    with pytest.raises(ValueError, match="27 kernel offsets, more than this kernel's 9"):
        small(y)
    with pytest.raises(ValueError, match="ignores dilation"):
        SubMConv3d(3, 3, 3, dilation=2, semantics="spconv1")


def test_spconv1_strided_reuse_and_the_inverse_of_another_shape(form) -> None:
    """A strided convolution whose key exists runs on the stored map (spconv 1.x reuses any key): a 3x3x3 kernel on
    a stored 3x1x3 map is the 3x1x3 convolution with its first 9 slices; a kernel with fewer offsets than the map is
    refused; an inverse needs the same number of offsets, not the same shape."""
    x = cloud(2)
    down = SparseConv3d(3, 4, (3, 1, 3), stride=2, padding=(1, 0, 1), indice_key="d", semantics="spconv1").double()
    again = SparseConv3d(3, 4, 3, stride=2, padding=(1, 0, 1), indice_key="d", semantics="spconv1").double()
    y, y2 = down(x), again(x)
    ref = SparseConv3d(3, 4, (3, 1, 3), stride=2, padding=(1, 0, 1)).double()
    ref.weight.data = again.kernel_matrices().detach()[:9].reshape(3, 1, 3, 3, 4).permute(4, 0, 1, 2, 3)
    ref.bias.data = again.bias.detach()
    want = ref(x)
    assert torch.equal(y2.indices, y.indices) and torch.equal(want.indices, y.indices)
    assert torch.allclose(y2.features, want.features, rtol=1e-12, atol=1e-12)
    bigger = SparseConv3d(3, 4, 3, stride=2, padding=1, indice_key="e", semantics="spconv1").double()
    smaller = SparseConv3d(3, 4, (3, 1, 3), stride=2, padding=1, indice_key="e", semantics="spconv1").double()
    bigger(x)
    with pytest.raises(ValueError, match="27 kernel offsets, more than this kernel's 9"):
        smaller(x)
    with pytest.raises(ValueError, match="kernel of 27 offsets, but the convolution it inverts had 9"):
        SparseInverseConv3d(4, 3, 3, indice_key="d", semantics="spconv1").double()(y)
    up = SparseInverseConv3d(4, 3, (1, 3, 3), indice_key="d", semantics="spconv1").double()  # 9 offsets: accepted
    assert torch.equal(up(y).indices, x.indices)


def test_spconv2_refuses_what_spconv_2x_refuses_and_keeps_new_keys_downstream() -> None:
    x = cloud(3)
    a = SubMConv3d(3, 3, (1, 3, 3), indice_key="bef").double()
    y = a(x)
    with pytest.raises(ValueError, match=r"subm with same indice_key must have same kernel size, expect \[1, 3, 3\], "
                                         r"this layer \[3, 1, 3\]"):
        SubMConv3d(3, 3, (3, 1, 3), indice_key="bef").double()(y)
    with pytest.raises(ValueError, match="same dilation"):
        SubMConv3d(3, 3, (1, 3, 3), dilation=2, indice_key="bef").double()(y)
    with pytest.raises(ValueError, match="same num of indices"):
        fewer = SparseConvTensor(x.features[1:], x.indices[1:], SHAPE, 2, dict(y.indice_dict))
        SubMConv3d(3, 3, (1, 3, 3), indice_key="bef").double()(fewer)
    down = SparseConv3d(3, 3, 3, stride=2, padding=1, indice_key="d").double()
    z = down(y)
    with pytest.raises(ValueError, match="indice_key 'd' already exists"):
        SparseConv3d(3, 3, 3, stride=2, padding=1, indice_key="d").double()(y.derived(
            y.features, indice_dict=dict(z.indice_dict)))  # the same key again (spconv 2.x asserts)
    with pytest.raises(ValueError, match="same spatial structure"):
        SparseInverseConv3d(3, 3, 3, indice_key="d").double()(z.derived(z.features, spatial_shape=[9, 9, 9]))
    # copies: a key made downstream is not seen upstream, so parallel branches may reuse a name
    assert "bef" in y.indice_dict and "bef" not in x.indice_dict and "d" not in y.indice_dict
    b = SubMConv3d(3, 3, (3, 1, 1), indice_key="bef").double()(x)  # another branch from x: its own map
    assert b.indice_dict["bef"].kernel == (3, 1, 1)


def test_a_tensors_indices_are_checked_and_the_first_bad_row_named() -> None:
    f = torch.zeros(3, 2)
    ok = torch.tensor([[0, 0, 0, 0], [0, 1, 2, 3], [1, 5, 6, 4]], dtype=torch.int32)
    SparseConvTensor(f, ok, SHAPE, 2)
    for row, bad, msg in [(1, [0, 1, 2, 3], r"row 2 = \(0, 1, 2, 3\) repeats row 1"),
                          (2, [0, -1, 0, 0], r"row 2 = \(0, -1, 0, 0\): coordinate \(-1, 0, 0\) outside the grid"),
                          (2, [0, 6, 0, 0], r"row 2 = \(0, 6, 0, 0\): coordinate \(6, 0, 0\) outside"),
                          (2, [0, 0, 0, 5], r"coordinate \(0, 0, 5\) outside the grid \[0, 6\) x \[0, 7\) x \[0, 5\)"),
                          (2, [-1, 0, 0, 1], r"row 2 = \(-1, 0, 0, 1\): batch index -1 outside \[0, 2\)"),
                          (2, [2, 0, 0, 1], r"batch index 2 outside \[0, 2\)")]:
        idx = ok.clone()
        idx[2] = torch.tensor(bad)
        with pytest.raises(ValueError, match=msg):
            SparseConvTensor(f, idx, SHAPE, 2)
    dup = torch.tensor([[0, 1, 1, 1], [0, 2, 2, 2], [0, 1, 1, 1], [0, 2, 2, 2]], dtype=torch.int32)
    with pytest.raises(ValueError, match=r"row 2 = \(0, 1, 1, 1\) repeats row 0"):  # the first repeat, by row
        SparseConvTensor(torch.zeros(4, 2), dup, SHAPE, 1)


def test_keywords_and_a_dtype_mismatch_names_the_layer() -> None:
    SubMConv3d(3, 3, 3, algo=None, fp32_accum=False, use_hash=False)  # spconv's speed-only keywords
    with pytest.raises(TypeError, match="unexpected keyword argument 'output_padding'"):
        SparseConv3d(3, 3, 3, output_padding=1)
    with pytest.raises(ValueError, match="semantics must be one of spconv1, spconv2"):
        SubMConv3d(3, 3, 3, semantics="spconv3")
    net = torch.nn.Sequential(torch.nn.Module(), SubMConv3d(3, 3, 3, indice_key="k"))
    name_modules(net, "net.")
    with pytest.raises(ValueError, match=r"net\.1: SubMConv3d\(3 -> 3, kernel \(3, 3, 3\), indice_key='k'\): "
                                         r"torch.float64 features against torch.float32 weights"):
        net[1](cloud())
    assert SubMConv3d(3, 3, 3, name="mine").describe().startswith("mine: ")


def test_spconv1_shares_the_callers_dictionary_and_fresh_starts_a_new_one() -> None:
    """spconv 1.x's dictionary is the input tensor's own: model A writes its map into ``x.indice_dict`` and model B,
    run on ``x`` afterwards, reuses it under the same key whatever its own kernel. ``x.fresh()`` gives B what a newly
    built tensor would; ``replace_feature`` keeps the dictionary, ``fresh`` does not (the same features, though)."""
    torch.manual_seed(0)
    model_a = torch.nn.Sequential(SubMConv3d(3, 3, (1, 3, 3), indice_key="k", semantics="spconv1")).double()
    model_b = torch.nn.Sequential(SubMConv3d(3, 2, 3, indice_key="k", semantics="spconv1")).double()
    x = cloud()
    rebuilt = SparseConvTensor(x.features, x.indices, x.spatial_shape, x.batch_size)
    want = model_b(rebuilt).features
    model_a(x)
    assert x.indice_dict["k"].kernel == (1, 3, 3)  # A's map, in the caller's tensor
    shared = model_b(x).features  # on A's 1x3x3 map: B's first 9 kernel slices only
    assert not torch.allclose(shared, want)
    fresh = x.fresh()
    assert fresh.indice_dict == {} and fresh.indice_dict is not x.indice_dict
    assert fresh.features is x.features and fresh.indices is x.indices
    assert (fresh.spatial_shape, fresh.batch_size) == (x.spatial_shape, x.batch_size)
    assert torch.equal(model_b(fresh).features, want)
    assert "k" in x.indice_dict and x.replace_feature(x.features * 2).indice_dict is x.indice_dict
    # spconv 2.x's semantics never write into the input's dictionary: nothing to start afresh
    y = cloud()
    SubMConv3d(3, 3, (1, 3, 3), indice_key="k").double()(y)
    assert y.indice_dict == {}
