"""Gather, GEMM per kernel offset, scatter-add: a sparse convolution on a rulebook, with its own backward.

For kernel index k with pairs (in rows I_k, out rows O_k): out[O_k] += in[I_k] W_k. The backward recomputes the
gathers instead of keeping them (autograd would store P x C_in floats): grad W_k = in[I_k]^T grad[O_k] and
grad in[I_k] += grad[O_k] W_k^T.

Deterministic on every device by construction: within one kernel offset no two pairs share an output row (nor an
input row), so each scatter-add (``index_add_``) writes distinct rows — one addition per row per offset, the
offsets in their fixed order — and the order its threads run in (atomics on CUDA) cannot change a bit; the maps
themselves come from sorts and searches, deterministic too. Under ``DISTILKIT_DETERMINISTIC`` PyTorch still routes
CUDA's ``index_add_`` through ``index_put_(accumulate=True)``'s sorted path (slower, and reading the index's range
to the host in some versions): since each of these scatter-adds writes distinct rows, they run with PyTorch's flag
lowered for that call alone (:func:`_scatter_add`), the order fixed by the offsets' loop either way. The CPU tests run this same code (``tests/test_sparse.py``: shuffling an offset's pairs changes no bit). Under autocast (``train.precision: bf16 | fp16``) the products run in autocast's dtype and the sums in
float32 (as spconv accumulates half-precision products); the output has autocast's dtype.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import torch
from torch import Tensor

from distilkit.repro import set_deterministic
from distilkit.sparse.backend import Call, choose, library_conv, ran
from distilkit.sparse.form import form
from distilkit.sparse.rulebook import Rulebook
from distilkit.sparse.table import compute_dtypes, table_conv


def _scatter_add(out: Tensor, index: Tensor, values: Tensor) -> None:
    """``out.index_add_(0, index, values)`` for an ``index`` without repeats (one kernel offset's output rows, or its
    input rows in the backward): one addition per row, so the same bits whatever order the threads run in. On CUDA
    under PyTorch's deterministic algorithms the plain kernel is used all the same (the flag lowered for this call,
    restored after): the deterministic routing through ``index_put_`` sorts the index and syncs with the host for
    nothing here."""
    if out.device.type == "cuda" and torch.are_deterministic_algorithms_enabled():
        warn_only = torch.is_deterministic_algorithms_warn_only_enabled()
        set_deterministic(False)
        try:
            out.index_add_(0, index, values)
        finally:
            set_deterministic(True, warn_only=warn_only)
        return
    out.index_add_(0, index, values)


@cache
def _function(device_type: str) -> type[torch.autograd.Function]:
    """The convolution's autograd function for one device type, declaring its autocast behaviour there
    (``torch.amp.custom_fwd``/``custom_bwd``): under autocast the gathers and products run in autocast's dtype
    (bf16 or fp16) and the scatter-adds sum in float32, the backward under the forward's autocast state; without
    autocast everything runs in the features' dtype, as before."""

    class _RulebookConv(torch.autograd.Function):
        @staticmethod
        @torch.amp.custom_fwd(device_type=device_type)
        def forward(ctx: Any, features: Tensor, weight: Tensor, in_idx: Tensor, out_idx: Tensor, bounds: list[int],
                    rows_out: int) -> Tensor:
            dtype, acc = compute_dtypes(features)
            f, w = features.to(dtype), weight.to(dtype)
            out = features.new_zeros((rows_out, weight.shape[2]), dtype=acc)
            for k in range(weight.shape[0]):
                s, e = bounds[k], bounds[k + 1]
                if e > s:
                    _scatter_add(out, out_idx[s:e], torch.mm(f.index_select(0, in_idx[s:e]), w[k]).to(acc))
            ctx.save_for_backward(f, w, in_idx, out_idx)
            ctx.bounds, ctx.dtypes = bounds, (features.dtype, weight.dtype, acc)
            return out.to(dtype)

        @staticmethod
        @torch.amp.custom_bwd(device_type=device_type)
        def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
            f, w, in_idx, out_idx = ctx.saved_tensors
            bounds = ctx.bounds
            features_dtype, weight_dtype, acc = ctx.dtypes
            need_f, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
            grad_f = f.new_zeros(f.shape, dtype=acc) if need_f else None
            grad_w = w.new_zeros(w.shape, dtype=acc) if need_w else None
            grad = grad.to(f.dtype).contiguous()
            for k in range(w.shape[0]):
                s, e = bounds[k], bounds[k + 1]
                if e == s:
                    continue
                g = grad.index_select(0, out_idx[s:e])
                if grad_w is not None:
                    grad_w[k] = torch.mm(f.index_select(0, in_idx[s:e]).t(), g).to(acc)
                if grad_f is not None:
                    _scatter_add(grad_f, in_idx[s:e], torch.mm(g, w[k].t()).to(acc))
            return (grad_f.to(features_dtype) if grad_f is not None else None,
                    grad_w.to(weight_dtype) if grad_w is not None else None, None, None, None, None)

    return _RulebookConv


def rulebook_conv(features: Tensor, weight: Tensor, book: Rulebook, rows_out: int,
                  bias: Tensor | None = None) -> Tensor:
    """(rows_out, C_out) = ``bias`` + the convolution of (N, C_in) ``features`` on ``book`` with ``weight`` (K,
    C_in, C_out), on the backend :func:`distilkit.sparse.backend.choose` picks for the features' device and, on the
    torch path, in the form :func:`form` picks (the table form adds the bias inside its float32 accumulator)."""
    if weight.shape[0] != len(book.bounds) - 1:
        raise ValueError(f"sparse convolution: {weight.shape[0]} kernel offsets in the weight, "
                         f"{len(book.bounds) - 1} in the neighbour map")
    if features.shape[0] != book.in_indices.shape[0]:
        raise ValueError(f"sparse convolution: {features.shape[0]} input rows, the neighbour map reads "
                         f"{book.in_indices.shape[0]}")
    if book.out_indices.shape[0] != rows_out:
        raise ValueError(f"sparse convolution: the neighbour map has {book.out_indices.shape[0]} output rows, "
                         f"{rows_out} asked for")
    pairs = book.pairs_host
    backend = "torch"
    if pairs > 0:  # an empty map never reaches a library (spconv asserts): zeros (gradients zeros) on the torch path
        backend = choose(features.device.type, Call.of(features, weight, pairs))
        ran(backend)
    if backend != "torch":
        out = library_conv(backend, features, weight, book, rows_out)
    elif form(features.device.type) == "table":
        return table_conv(features, weight, bias, book)
    else:
        out = _function(features.device.type).apply(features, weight, book.in_idx, book.out_idx, book.bounds,
                                                     rows_out)
    if bias is not None:
        out = out + bias
    device = features.device.type
    if torch.is_autocast_enabled(device):  # autocast's dtype out, as the table form and a 1x1x1 layer give
        out = out.to(torch.get_autocast_dtype(device))
    return out


__all__ = ["rulebook_conv"]
