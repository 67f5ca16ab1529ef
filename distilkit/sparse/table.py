"""A sparse convolution as gathers and GEMMs over a neighbour table: no loop over the kernel's offsets.

The table of a map (:func:`tables`) is (N_out, K) int64: entry (o, k) is the input row that kernel offset k reads for
output row o, or N_in (a zero row appended to the input) where that neighbour is absent. It is well defined because
within one offset no two pairs share an output row (nor an input row: :mod:`distilkit.sparse.function`). With it a
convolution is, for each chunk of output rows R,

    out[R] = bias + gather(in_pad, T[R]) (|R|, K C_in)  @  W (K C_in, C_out),

the weight gradient is ``sum_R gather(in_pad, T[R])^T @ grad[R]`` (one GEMM a chunk, the chunks summed in their
order), and the input gradient is the same gather-GEMM on the transposed table T' (N_in, K) — entry (n, k) the
output row that reads input row n through offset k — against the blocks W_k^T: ``grad_in[R'] = gather(grad_pad,
T'[R']) @ W'`` with W' (K C_out, C_in). (For a submanifold map without duplicate sites T' is T with its columns
reversed; it is built the same way for every kind.) No atomics, no scatter: the same bits on every run of a device,
whatever its threads do; the sums run in an order of their own, so the result equals the per-offset loop's to
rounding, not bit for bit (float64: ``tests/test_sparse_table.py``).

Rows are chunked so that a gathered block stays within :data:`BUDGET` bytes (a chunk of one row at least). The
table costs K times the gathered width of the pairs that exist (27 for a 3x3x3 kernel where a LiDAR scan's voxels
have ~5-10 neighbours), so it does more arithmetic than the loop, in two or three kernel launches a chunk instead of
~10 an offset: on a GPU the launches dominate up to ~10^6 voxels; on the CPU :mod:`distilkit.sparse.function`
keeps whichever form ``distilkit bench sparse`` measured faster there.

Under autocast (``train.precision: bf16 | fp16``) the weight is cast once a call (one layer call a step), the
gathers and the GEMM's operands are in autocast's dtype, the GEMM accumulates in float32 inside — returning float32
where torch offers it (``out_dtype`` on CUDA), else its own dtype's result converted once — the bias is added to the
float32 result, and the output is cast to autocast's dtype once: no cast per kernel offset.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import torch
from torch import Tensor

BUDGET = 128 << 20  # bytes of one gathered block (rows x K x channels); a chunk has one row at least


def tables(book: Any) -> tuple[Tensor, Tensor]:
    """(T (N_out, K), T' (N_in, K)) of ``book``, int32 (int64 past 2^31 rows), kept in its cache: absent entries
    hold N_in in T (the input's zero row) and N_out in T'. Built from the host-side bounds with one ``index_put_`` an offset: no host sync."""
    if "table" in book.cache:
        return book.cache["table"]
    n_in, n_out, volume = book.in_indices.shape[0], book.out_indices.shape[0], book.volume
    device = book.in_idx.device
    index = torch.int32 if max(n_in, n_out) < 2 ** 31 - 1 else torch.int64  # half the memory where it fits
    forward = torch.full((n_out, volume), n_in, dtype=index, device=device)
    backward = torch.full((n_in, volume), n_out, dtype=index, device=device)
    for k in range(volume):
        s, e = book.bounds[k], book.bounds[k + 1]
        if e > s:
            forward[:, k].index_put_((book.out_idx[s:e],), book.in_idx[s:e].to(index))
            backward[:, k].index_put_((book.in_idx[s:e],), book.out_idx[s:e].to(index))
    book.cache["table"] = forward, backward
    return book.cache["table"]


def _rows(volume: int, channels: int, itemsize: int) -> int:
    """Rows of one chunk: a gathered (rows, volume, channels) block within :data:`BUDGET`."""
    return max(1, BUDGET // max(volume * channels * itemsize, 1))


def _gather(x_pad: Tensor, table: Tensor) -> Tensor:
    """(rows, K C) rows of ``x_pad`` at a (rows, K) table (one ``index_select`` of the flattened table: a plain
    gather, several times faster than advanced indexing on the CPU)."""
    return x_pad.index_select(0, table.reshape(-1)).view(table.shape[0], -1)


def _padded(x: Tensor) -> Tensor:
    """``x`` with a zero row appended (the absent neighbour's row)."""
    return torch.cat([x, x.new_zeros((1, x.shape[1]))])


@cache
def _out_dtype_ok(device_type: str, dtype: torch.dtype) -> bool:
    """Whether ``torch.mm(..., out_dtype=torch.float32)`` runs for ``dtype`` operands on ``device_type`` (CUDA's
    half-precision GEMMs; not the CPU's in torch 2.13): probed once."""
    if device_type == "cpu":
        return False
    try:
        a = torch.zeros((2, 2), dtype=dtype, device=device_type)
        return torch.mm(a, a, out_dtype=torch.float32).dtype == torch.float32
    except (RuntimeError, NotImplementedError, TypeError):
        return False


def _mm_acc(a: Tensor, b: Tensor, acc: torch.dtype) -> Tensor:
    """a @ b in ``acc`` (float32 for half operands): the GEMM's own float32 result where torch offers it, else its
    result converted once."""
    if a.dtype == acc:
        return torch.mm(a, b)
    if _out_dtype_ok(a.device.type, a.dtype):
        return torch.mm(a, b, out_dtype=acc)
    return torch.mm(a, b).to(acc)


def compute_dtypes(features: Tensor) -> tuple[torch.dtype, torch.dtype]:
    """(the products' dtype, the sums' dtype): autocast's dtype where it is on for the features' device, with sums in
    float32; else the features' own dtype for both (the layer checks that the weight has it). Both forms use it."""
    device = features.device.type
    if torch.is_autocast_enabled(device):
        return torch.get_autocast_dtype(device), torch.float32
    return features.dtype, features.dtype


def _forward(f: Tensor, w: Tensor, bias: Tensor | None, table: Tensor, acc: torch.dtype) -> Tensor:
    """(N_out, C_out) in ``acc``: bias + gather(f_pad, T) @ w, a chunk of rows at a time."""
    n_out, volume = table.shape
    c_in, c_out = w.shape[1], w.shape[2]
    flat = w.reshape(volume * c_in, c_out)
    f_pad = _padded(f)
    out = f.new_empty((n_out, c_out), dtype=acc)
    step = _rows(volume, c_in, f.element_size())
    for s in range(0, n_out, step):
        block = _gather(f_pad, table[s:s + step])
        out[s:s + step] = _mm_acc(block, flat, acc)
    if bias is not None:
        out += bias.to(acc)
    return out


@cache
def _function(device_type: str) -> type[torch.autograd.Function]:
    """The table convolution's autograd function for one device type (autocast declared as in
    :func:`distilkit.sparse.function._function`)."""

    class _TableConv(torch.autograd.Function):
        @staticmethod
        @torch.amp.custom_fwd(device_type=device_type)
        def forward(ctx: Any, features: Tensor, weight: Tensor, bias: Tensor | None, table: Tensor,
                    back: Tensor) -> Tensor:
            dtype, acc = compute_dtypes(features)
            f, w = features.to(dtype), weight.to(dtype)  # the weight cast once a call, never per offset
            out = _forward(f, w, bias, table, acc)
            ctx.save_for_backward(f, w, table, back)
            ctx.dtypes = (features.dtype, weight.dtype, None if bias is None else bias.dtype, acc)
            return out.to(dtype)

        @staticmethod
        @torch.amp.custom_bwd(device_type=device_type)
        def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
            f, w, table, back = ctx.saved_tensors
            features_dtype, weight_dtype, bias_dtype, acc = ctx.dtypes
            need_f, need_w, need_b = ctx.needs_input_grad[:3]
            volume, c_in, c_out = w.shape
            g = grad.to(f.dtype).contiguous()
            grad_b = grad.to(acc).sum(0).to(bias_dtype) if need_b else None
            grad_w = None
            if need_w:
                f_pad = _padded(f)
                grad_w = w.new_zeros((volume * c_in, c_out), dtype=acc)
                step = _rows(volume, c_in, f.element_size())
                for s in range(0, table.shape[0], step):
                    block = _gather(f_pad, table[s:s + step])
                    grad_w += _mm_acc(block.t(), g[s:s + step], acc)
                grad_w = grad_w.reshape(volume, c_in, c_out).to(weight_dtype)
            grad_f = None
            if need_f:  # the same gather-GEMM on the transposed table, against the blocks W_k^T
                grad_f = _forward(g, w.transpose(1, 2), None, back, acc).to(features_dtype)
            return grad_f, grad_w, grad_b, None, None

    return _TableConv


def table_conv(features: Tensor, weight: Tensor, bias: Tensor | None, book: Any) -> Tensor:
    """(N_out, C_out) = ``bias`` + the convolution of (N_in, C_in) ``features`` on ``book`` with ``weight`` (K,
    C_in, C_out), through its neighbour tables."""
    table, back = tables(book)
    return _function(features.device.type).apply(features, weight, bias, table, back)


__all__ = ["BUDGET", "compute_dtypes", "table_conv", "tables"]
