"""Gather, GEMM per kernel offset, scatter-add: a sparse convolution on a rulebook, with its own backward.

For kernel index k with pairs (in rows I_k, out rows O_k): out[O_k] += in[I_k] W_k. The backward recomputes the
gathers instead of keeping them (autograd would store P x C_in floats): grad W_k = in[I_k]^T grad[O_k] and
grad in[I_k] += grad[O_k] W_k^T. ``index_add_`` accumulates in pair order on the CPU, so a run gives the same bits in
every process.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from distilkit.sparse.rulebook import Rulebook


class _RulebookConv(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, features: Tensor, weight: Tensor, in_idx: Tensor, out_idx: Tensor, bounds: list[int],
                rows_out: int) -> Tensor:
        out = features.new_zeros((rows_out, weight.shape[2]))
        for k in range(weight.shape[0]):
            s, e = bounds[k], bounds[k + 1]
            if e > s:
                out.index_add_(0, out_idx[s:e], torch.mm(features.index_select(0, in_idx[s:e]), weight[k]))
        ctx.save_for_backward(features, weight, in_idx, out_idx)
        ctx.bounds = bounds
        return out

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:
        features, weight, in_idx, out_idx = ctx.saved_tensors
        bounds = ctx.bounds
        need_f, need_w = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_f = torch.zeros_like(features) if need_f else None
        grad_w = torch.zeros_like(weight) if need_w else None
        grad = grad.contiguous()
        for k in range(weight.shape[0]):
            s, e = bounds[k], bounds[k + 1]
            if e == s:
                continue
            g = grad.index_select(0, out_idx[s:e])
            if grad_w is not None:
                grad_w[k] = torch.mm(features.index_select(0, in_idx[s:e]).t(), g)
            if grad_f is not None:
                grad_f.index_add_(0, in_idx[s:e], torch.mm(g, weight[k].t()))
        return grad_f, grad_w, None, None, None, None


def rulebook_conv(features: Tensor, weight: Tensor, book: Rulebook, rows_out: int) -> Tensor:
    """(rows_out, C_out) = the convolution of (N, C_in) ``features`` on ``book`` with ``weight`` (K, C_in, C_out)."""
    if weight.shape[0] != len(book.bounds) - 1:
        raise ValueError(f"sparse convolution: {weight.shape[0]} kernel offsets in the weight, "
                         f"{len(book.bounds) - 1} in the neighbour map")
    return _RulebookConv.apply(features, weight, book.in_idx, book.out_idx, book.bounds, rows_out)


__all__ = ["rulebook_conv"]
