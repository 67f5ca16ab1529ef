"""distilkit.sparse against dense convolution (float64, values and gradients of inputs and weights) for every kind
and Cylinder3D's kernels, with empty samples and voxels at the grid's edges, on the device of ``--device``; the same
bits in two processes."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d

KERNELS = [(1, 3, 3), (3, 1, 3), (3, 3, 1), (3, 3, 3)]
SHAPE = (7, 6, 5)


@pytest.fixture(params=["loop", "table"])
def form(request: pytest.FixtureRequest):
    """The torch path's two forms (:mod:`distilkit.sparse.function`'s loop over offsets, :mod:`distilkit.sparse.table`'s
    neighbour table): each test that takes it holds for both."""
    from distilkit.sparse.form import using_form

    with using_form(request.param):
        yield request.param


def cloud(seed: int = 0, batch: int = 3, channels: int = 4, n: int = 40, empty: int | None = 1,
          device: torch.device = torch.device("cpu")) -> SparseConvTensor:
    """Random active voxels of ``batch`` grids (sample ``empty`` has none), with the grid's corners included."""
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(batch):
        if b == empty:
            continue
        coords = torch.stack([torch.randint(0, s, (n,), generator=g) for s in SHAPE], dim=1)
        corners = torch.tensor([[0, 0, 0], [s - 1 for s in SHAPE], [0, SHAPE[1] - 1, 0]])
        coords = torch.unique(torch.cat([coords, corners]), dim=0)
        rows.append(torch.cat([torch.full((len(coords), 1), b), coords], dim=1))
    idx = torch.cat(rows).int()
    feats = torch.randn(len(idx), channels, generator=g, dtype=torch.float64)
    return SparseConvTensor(feats.to(device), idx.to(device), SHAPE, batch)


def dense_weight(conv) -> torch.Tensor:
    """spconv's (out, k0, k1, k2, in) as conv3d's (out, in, k0, k1, k2)."""
    return conv.weight.permute(0, 4, 1, 2, 3)


def at(dense: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows of a dense (B, C, X, Y, Z) grid at (N, 4) indices."""
    i = idx.long()
    return dense[i[:, 0], :, i[:, 1], i[:, 2], i[:, 3]]


def grads_match(sparse_out, x, conv, dense_fn, out_idx) -> None:
    """The same loss through both: values, and gradients of the features and of the weight and bias."""
    g = torch.Generator().manual_seed(9)
    r = torch.randn(sparse_out.features.shape, generator=g, dtype=torch.float64).to(sparse_out.features.device)
    (sparse_out.features * r).sum().backward()
    got_f, got_w, got_b = x.features.grad.clone(), conv.weight.grad.clone(), conv.bias.grad.clone()
    x.features.grad, conv.weight.grad, conv.bias.grad = None, None, None
    dense_in = x.dense().detach().requires_grad_()
    ref = at(dense_fn(dense_in), out_idx)
    assert torch.allclose(sparse_out.features, ref, rtol=1e-12, atol=1e-12)
    (ref * r).sum().backward()
    assert torch.allclose(got_f, at(dense_in.grad, x.indices), rtol=1e-12, atol=1e-12)
    assert torch.allclose(got_w, conv.weight.grad, rtol=1e-12, atol=1e-12)
    assert torch.allclose(got_b, conv.bias.grad, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("dilation", [1, 2])
def test_submanifold_equals_dense_conv3d_at_the_active_sites(kernel, dilation, device, form) -> None:
    x = cloud(device=device)
    x.features.requires_grad_()
    conv = SubMConv3d(4, 5, kernel, dilation=dilation, indice_key="subm").double().to(device)
    out = conv(x)
    assert torch.equal(out.indices, x.indices) and out.spatial_shape == list(SHAPE)
    pad = tuple((k - 1) // 2 * dilation for k in kernel)
    grads_match(out, x, conv, lambda d: F.conv3d(d, dense_weight(conv), conv.bias, padding=pad, dilation=dilation),
                x.indices)
    again = out.replace_feature(out.features.detach()[:, :4].contiguous())  # the map is reused by its key
    assert "subm" not in x.indice_dict and out.indice_dict["subm"] is conv.rulebook(again)  # spconv 2.x: downstream


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("stride,padding,dilation", [(2, 1, 1), ((2, 2, 1), (1, 1, 0), 1), (1, 0, 1), (2, 0, 2)])
def test_strided_equals_dense_conv3d_and_its_active_sites_are_those_reached(kernel, stride, padding, dilation,
                                                                            device, form) -> None:
    x = cloud(1, device=device)
    x.features.requires_grad_()
    conv = SparseConv3d(4, 3, kernel, stride=stride, padding=padding, dilation=dilation, indice_key="down").double()
    conv = conv.to(device)
    out = conv(x)
    fn = lambda d: F.conv3d(d, dense_weight(conv), conv.bias, stride=stride, padding=padding, dilation=dilation)  # noqa: E731
    ref = fn(x.dense().detach())
    assert list(ref.shape[2:]) == out.spatial_shape
    reached = F.conv3d((x.dense().detach().abs().sum(1, keepdim=True) > 0).double(),
                       torch.ones(1, 1, *kernel, dtype=torch.float64, device=device), stride=stride, padding=padding,
                       dilation=dilation)[:, 0] > 0
    assert torch.equal(torch.sort(reached.nonzero().int(), dim=0)[0], torch.sort(out.indices, dim=0)[0])
    grads_match(out, x, conv, fn, out.indices)


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("stride,padding", [(2, 1), ((2, 2, 1), (1, 1, 0))])
def test_inverse_equals_conv_transpose3d_back_on_the_input_sites(kernel, stride, padding, device, form) -> None:
    x = cloud(2, device=device)
    down = SparseConv3d(4, 6, kernel, stride=stride, padding=padding, indice_key="k1").double().to(device)
    y = down(x)
    y = y.replace_feature(torch.randn(y.features.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
                          .to(device).requires_grad_())
    up = SparseInverseConv3d(6, 2, kernel, indice_key="k1").double().to(device)
    z = up(y)
    assert torch.equal(z.indices, x.indices) and z.spatial_shape == list(SHAPE)
    s, p = (stride,) * 3 if isinstance(stride, int) else stride, (padding,) * 3 if isinstance(padding, int) else padding
    natural = [(o - 1) * si - 2 * pi + (k - 1) + 1 for o, si, pi, k in zip(y.spatial_shape, s, p, kernel)]
    extra = tuple(t - n for t, n in zip(SHAPE, natural))
    w_t = up.weight.permute(4, 0, 1, 2, 3)  # conv_transpose3d's (in, out, k0, k1, k2)
    grads_match(z, y, up, lambda d: F.conv_transpose3d(d, w_t, up.bias, stride=s, padding=p, output_padding=extra),
                x.indices)
    with pytest.raises(KeyError, match="indice_key='nope'"):
        SparseInverseConv3d(6, 2, kernel, indice_key="nope").double().to(device)(y)


def test_an_empty_batch_and_gradcheck(device, form) -> None:
    empty = SparseConvTensor(torch.zeros(0, 4, dtype=torch.float64, device=device, requires_grad=True),
                             torch.zeros(0, 4, dtype=torch.int32, device=device), SHAPE, 2)
    for conv in (SubMConv3d(4, 3, 3), SparseConv3d(4, 3, 3, stride=2, padding=1)):
        conv = conv.double().to(device)
        out = conv(empty)
        assert out.features.shape == (0, 3)
        out.features.sum().backward()
        assert conv.weight.grad is not None and not conv.weight.grad.any()
    x = cloud(4, batch=2, channels=2, n=6, empty=None, device=device)
    conv = SparseConv3d(2, 2, (3, 1, 3), stride=2, padding=1).double().to(device)
    book = __import__("distilkit.sparse.rulebook", fromlist=["strided"]).strided(
        x.indices, SHAPE, conv.kernel_size, conv.stride, conv.padding, conv.dilation)
    from distilkit.sparse.function import rulebook_conv

    assert torch.autograd.gradcheck(lambda f, w: rulebook_conv(f, w, book, book.out_indices.shape[0]),
                                    (x.features.requires_grad_(), conv.kernel_matrices().detach().requires_grad_()))


def test_weights_are_spconv_2s_layout_and_bad_input_is_named() -> None:
    conv = SubMConv3d(16, 32, (1, 3, 3), bias=False)
    assert tuple(conv.weight.shape) == (32, 1, 3, 3, 16) and conv.bias is None
    assert set(conv.state_dict()) == {"weight"}
    with pytest.raises(ValueError, match="odd kernel"):
        SubMConv3d(4, 4, 2).double()(cloud())
    with pytest.raises(ValueError, match="3 input channels, expected 4"):
        SubMConv3d(4, 4, 3)(SparseConvTensor(torch.zeros(2, 3), torch.tensor([[0, 0, 0, 0], [0, 0, 0, 1]],
                                                                          dtype=torch.int32), SHAPE, 1))
    with pytest.raises(ValueError, match=r"indices must be \(N, 4\)"):
        SparseConvTensor(torch.zeros(2, 3), torch.zeros(2, 3, dtype=torch.int32), SHAPE, 1)


SCRIPT = """
import hashlib, torch
from distilkit.sparse import SparseConvTensor, SubMConv3d, SparseConv3d, SparseInverseConv3d
torch.manual_seed(0)
g = torch.Generator().manual_seed(1)
idx = torch.unique(torch.cat([torch.zeros(3000, 1, dtype=torch.long),
                              torch.randint(0, 40, (3000, 3), generator=g)], 1), dim=0).int()
x = SparseConvTensor(torch.randn(len(idx), 16, generator=g, requires_grad=True), idx, (40, 40, 40), 1)
a, b = SubMConv3d(16, 16, 3, indice_key="s"), SparseConv3d(16, 16, 3, stride=2, padding=1, indice_key="d")
c = SparseInverseConv3d(16, 16, 3, indice_key="d")
out = c(b(a(x)))
out.features.square().sum().backward()
h = hashlib.sha256()
for t in (out.features, x.features.grad, a.weight.grad, b.weight.grad, c.weight.grad):
    h.update(t.detach().numpy().tobytes())
print(h.hexdigest())
"""


def test_two_processes_give_the_same_bits() -> None:
    started = [subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True) for _ in range(2)]  # at once
    outs = [p.communicate(timeout=300) for p in started]
    assert all(p.returncode == 0 for p in started), [err[-2000:] for _, err in outs]
    runs = [out for out, _ in outs]
    assert runs[0] == runs[1] and len(runs[0].strip()) == 64


def maps(x: SparseConvTensor) -> list:
    """Every kind of map: submanifold, strided, the strided one's inverse, and a dilated submanifold one."""
    from distilkit.sparse.rulebook import strided, submanifold

    book = strided(x.indices, SHAPE, (3, 3, 3), (2, 2, 2), (1, 1, 1), (1, 1, 1))
    return [submanifold(x.indices, SHAPE, (3, 3, 3), (1, 1, 1)), book, book.inverse(),
            submanifold(x.indices, SHAPE, (3, 1, 3), (2, 2, 2))]


def test_each_kernel_offset_writes_distinct_rows_so_the_scatter_order_cannot_change_the_bits(device) -> None:
    """Why the scatter-add is deterministic on every device: within one kernel offset no two pairs share an output
    row (forward) or an input row (the features' gradient), so whatever order the pairs of an offset are added in —
    atomics on CUDA included — each row receives one addition per offset, offsets in their fixed order. Tested as
    exactly that: the pairs of each offset shuffled give the same bits in the values and the features' gradient."""
    from distilkit.sparse.form import using_form
    from distilkit.sparse.function import rulebook_conv
    from distilkit.sparse.rulebook import Rulebook

    x = cloud(3, channels=5, n=60, device=device)
    g = torch.Generator().manual_seed(4)
    for book in maps(x):
        for k in range(book.volume):
            s, e = book.bounds[k], book.bounds[k + 1]
            assert book.out_idx[s:e].unique().numel() == e - s and book.in_idx[s:e].unique().numel() == e - s
        perm = torch.cat([s + torch.randperm(e - s, generator=g)
                          for s, e in zip(book.bounds[:-1], book.bounds[1:])]).to(device)
        shuffled = Rulebook(book.in_idx[perm], book.out_idx[perm], book.bounds, book.out_indices, book.out_shape,
                            book.in_indices, book.in_shape, book.kernel, book.dilation, book.subm)
        w = torch.randn(book.volume, 5, 3, generator=g, dtype=torch.float64).to(device)
        feats = torch.randn(book.in_indices.shape[0], 5, generator=g, dtype=torch.float64).to(device)
        results = []
        for b in (book, shuffled):
            f, wk = feats.clone().requires_grad_(), w.clone().requires_grad_()
            with using_form("loop"):  # the per-offset form's scatter-adds (the table form has none)
                out = rulebook_conv(f, wk, b, b.out_indices.shape[0])
            out.square().sum().backward()
            results.append((out.detach(), f.grad, wk.grad))
        (out_a, f_a, w_a), (out_b, f_b, w_b) = results
        assert torch.equal(out_a, out_b) and torch.equal(f_a, f_b)
        # the weight's gradient is a GEMM over an offset's pairs: its sum runs in the map's order, fixed by the map's
        # construction (sorts and searches), so shuffling it only moves the rounding
        torch.testing.assert_close(w_a, w_b, rtol=1e-12, atol=1e-12)
