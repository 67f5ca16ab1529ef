"""Cross entropy with a deterministic reduction on CUDA: the one place every CE of :mod:`distilkit.losses` goes through.

PyTorch flags ``F.cross_entropy``'s reduced forms as nondeterministic on CUDA: over (B, K, *S) logits (3-D and more,
whatever the weights) it runs ``nll_loss2d``, whose 'mean' and 'sum' add into one number with ``atomicAdd``
(``nll_loss2d_forward_out_cuda_template does not have a deterministic implementation``: an error under
``torch.use_deterministic_algorithms(True)``, one of a stage's ``nondeterministic_ops`` under distilkit's
``warn_only`` settings, :mod:`distilkit.repro`). Its unreduced form (``reduction='none'``) is not flagged: each
element's loss -w_y · log softmax(z)_y is written once, forward and backward. :func:`weighted_cross_entropy` reduces
that with ``Tensor.sum``, which is deterministic, and divides by the sum of the weights of the counted labels, as
``F.cross_entropy``'s 'mean' does.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

Reduction = Literal["mean", "sum", "none"]


def deterministic_form_needed(x: Tensor) -> bool:
    """Whether a loss on ``x`` should take its deterministic form rather than a PyTorch kernel flagged as
    nondeterministic: off the CPU (PyTorch's CPU kernels of these ops are deterministic), while
    ``torch.are_deterministic_algorithms_enabled()`` (distilkit's stages turn it on, :mod:`distilkit.repro`)."""
    return x.device.type != "cpu" and torch.are_deterministic_algorithms_enabled()


def weighted_cross_entropy(logits: Tensor, target: Tensor, weight: Tensor | None = None, ignore_index: int = -100,
                           reduction: Reduction = "mean", deterministic: bool | None = None) -> Tensor:
    """``F.cross_entropy(logits, target, weight, ignore_index=ignore_index, reduction=reduction)``, with the 'mean' and
    'sum' reductions computed deterministically where PyTorch's are flagged.

    Args:
        logits: (N, K) or ``(B, K, *S)`` raw scores; target: (N,) or ``(B, *S)`` class ids (long), ``ignore_index``
            where a position counts for nothing.
        weight: (K,) class weights, of ``logits``' dtype (as ``F.cross_entropy`` requires); a class of weight 0 counts
            for nothing, in the loss or in the denominator.
        reduction: 'mean' = Σ_i w_{y_i} ℓ_i / Σ_i w_{y_i} over the positions not ignored (NaN when that sum is 0, as
            ``F.cross_entropy``), 'sum' = Σ_i w_{y_i} ℓ_i, 'none' = w_{y_i} ℓ_i per position (0 where ignored).
        deterministic: the deterministic form — ``F.cross_entropy``'s unreduced losses, then ``sum`` and the
            division by the weights' sum — rather than PyTorch's fused reduction. Default: where it is needed,
            i.e. off the CPU while ``torch.are_deterministic_algorithms_enabled()`` (distilkit's stages turn that on).
            On the CPU the fused reduction is deterministic and faster (the two-pass form took 1.1–2.1× its time on
            a 2-core Xeon, forward and backward), and it keeps the CPU's results bitwise as before.

    The value equals ``F.cross_entropy``'s up to the order of the additions (the same in float64 to 1e-15, gradients
    too; tests/test_deterministic_forms.py).
    """
    if reduction not in ("mean", "sum", "none"):
        raise ValueError(f"weighted_cross_entropy: reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
    if deterministic is None:
        deterministic = deterministic_form_needed(logits)
    if reduction == "none" or not deterministic:
        return F.cross_entropy(logits, target, weight=weight, ignore_index=ignore_index, reduction=reduction)
    per = F.cross_entropy(logits, target, weight=weight, ignore_index=ignore_index, reduction="none")
    if reduction == "sum":
        return per.sum()
    counted = target != ignore_index
    if weight is None:
        total = counted.sum().to(per.dtype)
    else:  # the ignored positions' ids may lie outside [0, K): clamped for the look-up, then masked
        total = torch.where(counted, weight[target.clamp(0, weight.numel() - 1)], weight.new_zeros(())).sum()
    return per.sum() / total


__all__ = ["deterministic_form_needed", "weighted_cross_entropy"]
