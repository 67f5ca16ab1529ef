"""The neighbour-table form of the sparse convolution (:mod:`distilkit.sparse.table`): its tables, its values and
gradients against the per-offset loop and a float64 gradcheck on every kind of map (the dense-conv3d checks of
tests/test_sparse.py run on both forms), chunked rows, no host sync, and autocast without a cast per offset (the
bias inside the float32 sum, autocast's dtype out)."""

from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from host_syncs import host_syncs
from test_sparse import SHAPE, cloud
from distilkit.sparse import SparseConv3d, SparseConvTensor, SubMConv3d
from distilkit.sparse import table as table_module
from distilkit.sparse.form import FORM_ENV, form, using_form
from distilkit.sparse.function import rulebook_conv
from distilkit.sparse.rulebook import strided, submanifold
from distilkit.sparse.table import table_conv, tables


def maps(x: SparseConvTensor) -> list:
    """Submanifold (plain and dilated), strided (padded, uneven stride) and the strided map's inverse."""
    down = strided(x.indices, SHAPE, (3, 3, 3), (2, 2, 1), (1, 1, 0), (1, 1, 1))
    return [submanifold(x.indices, SHAPE, (3, 3, 3), (1, 1, 1)), submanifold(x.indices, SHAPE, (1, 3, 3), (2, 2, 2)),
            down, down.inverse()]


def test_the_tables_hold_each_pair_once_and_the_absent_row_elsewhere(device) -> None:
    x = cloud(0, device=device)
    for book in maps(x):
        forward, back = tables(book)
        n_in, n_out = book.in_indices.shape[0], book.out_indices.shape[0]
        assert forward.shape == (n_out, book.volume) and back.shape == (n_in, book.volume)
        for k in range(book.volume):
            s, e = book.bounds[k], book.bounds[k + 1]
            want = torch.full((n_out,), n_in, dtype=torch.long, device=device)
            want[book.out_idx[s:e]] = book.in_idx[s:e]
            assert torch.equal(forward[:, k].long(), want)
            want_back = torch.full((n_in,), n_out, dtype=torch.long, device=device)
            want_back[book.in_idx[s:e]] = book.out_idx[s:e]
            assert torch.equal(back[:, k].long(), want_back)
        assert tables(book) is tables(book)  # built once, kept with the map
    sub = maps(x)[0]
    forward, back = tables(sub)
    assert torch.equal(back, forward.flip(1))  # a submanifold map's transposed table is its table reversed


@pytest.mark.parametrize("bias", [False, True])
def test_table_equals_the_loop_in_value_and_every_gradient(bias, device) -> None:
    x = cloud(1, channels=5, n=50, device=device)
    g = torch.Generator().manual_seed(2)
    for book in maps(x):
        feats = torch.randn(book.in_indices.shape[0], 5, generator=g, dtype=torch.float64).to(device)
        w = torch.randn(book.volume, 5, 3, generator=g, dtype=torch.float64).to(device)
        b = torch.randn(3, generator=g, dtype=torch.float64).to(device) if bias else None
        r = torch.randn(book.out_indices.shape[0], 3, generator=g, dtype=torch.float64).to(device)
        got = []
        for name in ("loop", "table"):
            f, wk = feats.clone().requires_grad_(), w.clone().requires_grad_()
            bk = b.clone().requires_grad_() if b is not None else None
            with using_form(name):
                out = rulebook_conv(f, wk, book, book.out_indices.shape[0], bk)
            (out * r).sum().backward()
            got.append((out.detach(), f.grad, wk.grad, bk.grad if bk is not None else None))
        for a, c in zip(*got):
            if a is not None:
                torch.testing.assert_close(a, c, rtol=1e-12, atol=1e-12)


def test_gradcheck_of_the_table_form_on_every_kind_of_map(device) -> None:
    x = cloud(4, batch=2, channels=2, n=8, empty=None, device=device)
    g = torch.Generator().manual_seed(5)
    for book in maps(x):
        f = torch.randn(book.in_indices.shape[0], 2, generator=g, dtype=torch.float64).to(device).requires_grad_()
        w = torch.randn(book.volume, 2, 2, generator=g, dtype=torch.float64).to(device).requires_grad_()
        b = torch.randn(2, generator=g, dtype=torch.float64).to(device).requires_grad_()
        assert torch.autograd.gradcheck(lambda f, w, b: table_conv(f, w, b, book), (f, w, b))


def test_rows_in_chunks_give_the_one_chunk_result(monkeypatch, device) -> None:
    x = cloud(2, channels=4, n=60, device=device)
    book = maps(x)[0]
    g = torch.Generator().manual_seed(6)
    f = torch.randn(book.in_indices.shape[0], 4, generator=g, dtype=torch.float64).to(device)
    w = torch.randn(book.volume, 4, 3, generator=g, dtype=torch.float64).to(device)
    results = []
    for budget in (table_module.BUDGET, 27 * 4 * 8 * 7):  # one chunk; chunks of 7 rows (a ragged last one)
        monkeypatch.setattr(table_module, "BUDGET", budget)
        assert table_module._rows(book.volume, 4, 8) == (7 if budget < 10_000 else table_module._rows(27, 4, 8))
        fk, wk = f.clone().requires_grad_(), w.clone().requires_grad_()
        out = table_conv(fk, wk, None, book)
        out.square().sum().backward()
        results.append((out.detach(), fk.grad, wk.grad))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])  # rows: same sums
    torch.testing.assert_close(results[0][2], results[1][2], rtol=1e-12, atol=1e-12)  # the chunks' sum: rounding


def test_the_table_form_never_waits_for_the_device(device) -> None:
    x = cloud(3, device=device)
    book = submanifold(x.indices, SHAPE, (3, 3, 3), (1, 1, 1))
    w = torch.randn(book.volume, 4, 4, dtype=torch.float64, device=device, requires_grad=True)
    f = x.features.clone().requires_grad_()
    with host_syncs(device) as seen:
        table_conv(f, w, None, book).sum().backward()
    assert seen == [], seen


class _Casts(TorchDispatchMode):
    """Counts floating-point dtype conversions (``aten._to_copy``) by the number of elements they convert."""

    def __init__(self) -> None:
        super().__init__()
        self.sizes: list[int] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # type: ignore[no-untyped-def]
        kwargs = kwargs or {}
        if str(func) == "aten._to_copy.default" and kwargs.get("dtype") is not None and kwargs["dtype"].is_floating_point:
            self.sizes.append(args[0].numel())
        return func(*args, **kwargs)


def test_autocast_casts_once_a_call_not_once_an_offset_and_adds_the_bias_in_float32() -> None:
    idx = cloud(5, batch=1, n=80, empty=None).indices
    g = torch.Generator().manual_seed(7)
    feats = torch.randn(len(idx), 8, generator=g)
    conv = SubMConv3d(8, 6, 3, indice_key="a")
    ref = conv(SparseConvTensor(feats, idx, SHAPE, 1)).features
    counts = {}
    for name in ("loop", "table"):
        with using_form(name), torch.autocast("cpu", dtype=torch.bfloat16), _Casts() as casts:
            out = conv(SparseConvTensor(feats, idx, SHAPE, 1)).features
        assert out.dtype == torch.bfloat16  # autocast's dtype out (the bias inside, not promoting it to float32)
        assert (out.float() - ref).abs().max() <= 1e-2 * ref.abs().max()
        counts[name] = len(casts.sizes)
    assert counts["table"] <= 4 < 27 <= counts["loop"], counts  # features, weight, float32 result, output


def test_a_one_voxel_layer_and_a_strided_one_keep_autocasts_dtype_with_a_bias() -> None:
    x = cloud(6, batch=1, n=40, empty=None)
    x = SparseConvTensor(x.features.float(), x.indices, SHAPE, 1)
    for conv in (SubMConv3d(4, 3, 1), SparseConv3d(4, 3, 3, stride=2, padding=1)):
        ref = conv(x).features
        for name in ("loop", "table"):
            with using_form(name), torch.autocast("cpu", dtype=torch.bfloat16):
                out = conv(x).features
            assert out.dtype == torch.bfloat16
            assert (out.float() - ref).abs().max() <= 2e-2 * ref.abs().max()


def test_the_form_is_the_table_on_cuda_and_named_errors(monkeypatch) -> None:
    monkeypatch.delenv(FORM_ENV, raising=False)
    assert form("cuda") == "table" and form("cpu") == "loop"  # the CPU keeps the faster loop (README: sparse path)
    monkeypatch.setenv(FORM_ENV, "table")
    assert form("cpu") == "table"
    monkeypatch.setenv(FORM_ENV, "nope")
    with pytest.raises(ValueError, match="DISTILKIT_SPARSE_FORM='nope'"):
        form("cpu")
    with pytest.raises(ValueError, match="sparse form 'x'"):
        with using_form("x"):
            pass
    x = cloud(7)
    book = submanifold(x.indices, SHAPE, (3, 3, 3), (1, 1, 1))
    with pytest.raises(ValueError, match="3 input rows, the neighbour map reads"):
        rulebook_conv(x.features[:3], torch.zeros(27, 4, 2, dtype=torch.float64), book, book.out_indices.shape[0])


def test_the_size_benchmarks_copies_keep_each_voxels_neighbourhood() -> None:
    """``distilkit bench sparse-sizes`` grows a scan by copies side by side: as many voxels per copy, none twice, all
    inside the grid, and the pairs per voxel of the scan (copies do not touch where the scan leaves the grid's last
    plane empty)."""
    from distilkit.bench.sparse import tiled

    idx = cloud(8, batch=1, n=90, empty=None).indices
    idx = idx[idx[:, 1] < SHAPE[0] - 1]  # the last x plane empty: copies side by side do not touch along x
    idx = idx[idx[:, 2] < SHAPE[1] - 1]
    one = submanifold(idx, SHAPE, (3, 3, 3), (1, 1, 1))
    many, grid = tiled(idx, 5, SHAPE)
    assert grid == (SHAPE[0] * 3, SHAPE[1] * 2, SHAPE[2]) and len(many) == 5 * len(idx)
    assert torch.unique(many, dim=0).shape[0] == len(many) and (many[:, 1:] < torch.tensor(grid)).all()
    assert submanifold(many, grid, (3, 3, 3), (1, 1, 1)).pairs == 5 * one.pairs
