"""Distillation-DPO's generator loss (Zhang et al., arXiv 2504.11447; happyw1nd/DistillationDPO), with the gradient
the method intends.

The student completes one scan twice, from two noises; the completion closer to the ground truth is the winner, the
other the loser. Two auxiliary score networks are fitted to the winners and the losers; the student then moves the
winner as VSD would (towards the teacher's score, away from its auxiliary network's) and the loser the other way.
For the student both noise-prediction pairs are constants, so the loss is a stop-gradient surrogate whose gradient is

    d/d winner =  weight (eps_teacher_w - eps_aux_w) / numel,
    d/d loser  = -weight (eps_teacher_l - eps_aux_l) / numel.

The released generator loss multiplies the prediction differences by a quantity that does not depend on the
samples, so its gradient is exactly 0 (the stop-gradient mistake of ScoreLiDAR's code, seed_code.md §3.5); its
value, like :func:`~distilkit.losses.vsd.vsd`'s, is that of the surrogate, not of the DPO objective.
"""

from __future__ import annotations

from torch import Tensor

from distilkit.losses.vsd import vsd


def distillation_dpo(winner: Tensor, loser: Tensor, eps_teacher_w: Tensor, eps_aux_w: Tensor, eps_teacher_l: Tensor,
                     eps_aux_l: Tensor, weight: float | Tensor = 1.0) -> Tensor:
    """A scalar whose gradient is ``weight (eps_teacher_w - eps_aux_w) / numel`` for ``winner`` and
    ``-weight (eps_teacher_l - eps_aux_l) / numel`` for ``loser`` (numel: the elements of one completion); no
    gradient reaches the noise predictions. ``winner`` and ``loser`` are completions of the same scans (same shape);
    ``weight`` is w(t), a number or a tensor broadcastable to them."""
    if loser.shape != winner.shape:
        raise ValueError(f"distillation_dpo: winner {tuple(winner.shape)} and loser {tuple(loser.shape)} must be "
                         "completions of the same scans (one shape)")
    return vsd(winner, eps_teacher_w, eps_aux_w, weight) - vsd(loser, eps_teacher_l, eps_aux_l, weight)


__all__ = ["distillation_dpo"]
