"""Distillation-DPO's generator loss (Zhang et al., arXiv 2504.11447; happyw1nd/DistillationDPO).

The student completes one scan twice, from two noises; the completion closer to the ground truth is the winner, the
other the loser. Two auxiliary score networks are fitted to the winners and the losers; both completions are
re-noised with one t and eps, and the frozen teacher's and the auxiliary networks' noise predictions there are
constants for the student, so the loss is a stop-gradient surrogate.

**The sign: the paper and its code disagree.** The paper's eq. 16-18 print

    Grad = (1/w) [(eps_theta - eps_phi^l) dG^l - (eps_theta - eps_phi^w) dG^w],

which, descended, pushes the winner away from the teacher's score and pulls the loser toward it. The released code
(``trains/DistillationDPO.py``, the generator loss ``(teacher_w - aux_w)(...) - (teacher_l - aux_l)(...)``) does
the opposite: the winner moves as VSD would (towards the teacher's score, away from its auxiliary network's) and the
loser the other way. ``sign="release"`` (the default: it is the one that distils) has the gradient

    d/d winner =  weight (eps_teacher_w - eps_aux_w) / numel,
    d/d loser  = -weight (eps_teacher_l - eps_aux_l) / numel;

``sign="paper"`` negates both. (The released loss multiplies the prediction differences by ``x_t - x_0``, which
does not depend on the samples, so its gradient is exactly 0 — ScoreLiDAR's stop-gradient mistake, seed_code.md
§3.5; distilkit applies the gradient the code's sign intends.)

**Linear or bounded.** The surrogate above is linear in the implicit log-ratios (Diffusion-DPO, Wallace et al. 2024,
without its log-sigmoid), so nothing bounds how far the loser is pushed. ``beta`` gives the bounded form: with the
per-scene margin Delta_b = r_w - r_l of the implicit rewards r(x) = mean weight [(eps - eps_aux(x_t))^2 -
(eps - eps_teacher(x_t))^2] (how much better the teacher than the auxiliary network denoises x_t: the diffusion
bound on log p_teacher(x) - log p_student(x), eps the noise that made x_t), the loss is Diffusion-DPO's

    L = mean_b (2 / beta) softplus(-beta s Delta_b),     s = +1 (release) or -1 (paper),

whose gradient is the linear form's, scene by scene, times 2 sigmoid(-beta s Delta_b): equal to it at a zero margin,
vanishing once the winner is ahead by much more than 1 / beta. ``beta=None`` keeps the linear surrogate (whose value,
like :func:`~distilkit.losses.vsd.vsd`'s, is that of the surrogate, not of an objective).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

SIGNS = {"release": 1.0, "paper": -1.0}


def _per_scene(values: Tensor) -> Tensor:
    """(B,) sums over every axis but the first."""
    return values.reshape(values.shape[0], -1).sum(dim=1)


def _weight(weight: float | Tensor, like: Tensor) -> Tensor:
    """``weight`` in ``like``'s dtype and device (a number is made there: made in float32 and cast, a float64
    gradient would carry float32's rounding of it), broadcast to ``like``."""
    if isinstance(weight, Tensor):
        return weight.detach().to(device=like.device, dtype=like.dtype).expand_as(like)
    return torch.full_like(like, float(weight))


def implicit_reward(eps: Tensor, eps_teacher: Tensor, eps_aux: Tensor, weight: float | Tensor = 1.0) -> Tensor:
    """(B,) r = the per-scene mean of weight [(eps - eps_aux)^2 - (eps - eps_teacher)^2]: positive where the teacher
    denoises the re-noised completion better than the auxiliary network (the completion is more teacher-like)."""
    err = (eps - eps_aux).pow(2) - (eps - eps_teacher).pow(2)
    w = _weight(weight, err)
    return _per_scene(w * err) / (err[0].numel() if err.shape[0] else 1)


def distillation_dpo(winner: Tensor, loser: Tensor, eps_teacher_w: Tensor, eps_aux_w: Tensor, eps_teacher_l: Tensor,
                     eps_aux_l: Tensor, weight: float | Tensor = 1.0, *, sign: Literal["release", "paper"] = "release",
                     beta: float | None = None, noise_w: Tensor | None = None,
                     noise_l: Tensor | None = None) -> Tensor:
    """Distillation-DPO's generator loss for ``winner`` and ``loser`` (completions of the same scans, (B, M, 3)).

    Linear (``beta=None``): a scalar whose gradient is ``s weight (eps_teacher_w - eps_aux_w) / numel`` for the
    winner and ``-s weight (eps_teacher_l - eps_aux_l) / numel`` for the loser (s = +1 for ``sign="release"``, -1 for
    ``"paper"``; numel: the elements of the whole batch). Bounded (``beta > 0``; needs ``noise_w``, the eps that made
    the winner's x_t, and ``noise_l``, the loser's, default the same): Diffusion-DPO's (2 / beta) softplus(-beta s
    Delta) per scene, averaged, with the linear gradient of each scene times 2 sigmoid(-beta s Delta_b). No gradient
    reaches the noise predictions. ``weight`` is w(t), a number or a tensor broadcastable to the completions.
    """
    if loser.shape != winner.shape:
        raise ValueError(f"distillation_dpo: winner {tuple(winner.shape)} and loser {tuple(loser.shape)} must be "
                         "completions of the same scans (one shape)")
    for name, t in (("eps_teacher_w", eps_teacher_w), ("eps_aux_w", eps_aux_w), ("eps_teacher_l", eps_teacher_l),
                    ("eps_aux_l", eps_aux_l)):
        if t.shape != winner.shape:
            raise ValueError(f"distillation_dpo: {name} {tuple(t.shape)} must have the completions' shape "
                             f"{tuple(winner.shape)}")
    if sign not in SIGNS:
        raise ValueError(f"distillation_dpo: sign must be 'release' or 'paper', got {sign!r}")
    s = SIGNS[sign]
    numel = winner.numel()
    g_w = (_weight(weight, winner) * (eps_teacher_w - eps_aux_w).detach()).to(winner.dtype)
    g_l = (_weight(weight, loser) * (eps_teacher_l - eps_aux_l).detach()).to(loser.dtype)
    linear = s * (_per_scene(g_w * winner) - _per_scene(g_l * loser)) / numel  # (B,): the surrogate, scene by scene
    if beta is None:
        return linear.sum()
    if beta <= 0:
        raise ValueError(f"distillation_dpo: beta must be > 0 (or None for the linear form), got {beta}")
    if noise_w is None:
        raise ValueError("distillation_dpo: the bounded form (beta) needs noise_w, the noise that made x_t")
    noise_l = noise_w if noise_l is None else noise_l
    with torch.no_grad():
        margin = s * (implicit_reward(noise_w, eps_teacher_w, eps_aux_w, weight)
                      - implicit_reward(noise_l, eps_teacher_l, eps_aux_l, weight))  # (B,)
        value = (2.0 / beta) * F.softplus(-beta * margin)
        scale = 2.0 * torch.sigmoid(-beta * margin)
    return value.mean().to(winner.dtype) + (scale.to(winner.dtype) * (linear - linear.detach())).sum()


__all__ = ["distillation_dpo", "implicit_reward"]
