"""Variational score distillation (ScoreLiDAR eq. 9-11, after ProlificDreamer's VSD) as a surrogate loss.

The gradient of the KL objective with respect to the student's samples is w(t) (eps_teacher - eps_aux)
(eq. 11; for LiDiff's local noise x_t = x_0 + sigma_t eps, dx_t/dx_0 = I and w absorbs 1/sigma_t). Both
noise predictions are constants for the student, so the loss is the stop-gradient surrogate
``sum(sg(g) * samples) / numel`` whose gradient is exactly ``g / numel``. The released code's
``((eps_teacher - eps_aux) * (x_t - x_0)).mean()`` has a gradient of exactly zero (x_t - x_0 does not
depend on the samples; seed_code.md §3.5); this one does not.
"""

from __future__ import annotations

from torch import Tensor


def vsd(samples: Tensor, eps_teacher: Tensor, eps_aux: Tensor, weight: float | Tensor = 1.0) -> Tensor:
    """A scalar whose gradient with respect to ``samples`` is ``weight * (eps_teacher - eps_aux) / samples.numel()``.

    ``eps_teacher`` and ``eps_aux`` (the frozen teacher's and the auxiliary network's noise predictions at the
    re-noised samples) have the samples' shape and are detached here; ``weight`` is w(t), a number or a tensor
    broadcastable to the samples (e.g. (B, 1, 1) per scene). Its value is that of the surrogate, not of the KL.
    """
    if eps_teacher.shape != samples.shape or eps_aux.shape != samples.shape:
        raise ValueError(f"vsd: samples {tuple(samples.shape)}, eps_teacher {tuple(eps_teacher.shape)} and eps_aux "
                         f"{tuple(eps_aux.shape)} must have one shape")
    w = weight.detach() if isinstance(weight, Tensor) else weight
    g = (w * (eps_teacher.detach() - eps_aux.detach())).to(samples.dtype)
    if g.shape != samples.shape:
        g = g.expand_as(samples)
    return (g * samples).sum() / samples.numel()


__all__ = ["vsd"]
