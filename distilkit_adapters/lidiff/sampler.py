"""LiDiff's two samplers of the local-noise process x_t = x_0 + sigma_t eps (sigma_t = sqrt(1 - abar_t)).

* :func:`ddim` (the default): n network evaluations at "trailing" timesteps T(n-i)/n - 1 (n = 4: 999, 749, 499,
  249), each a deterministic DDIM step x_prev = x0_hat + sigma_prev eps_hat with x0_hat = x_t - sigma_t eps_hat, the
  last one returning x0_hat. It is the one consistent with how LiDiff *trains*: the process scales no signal, so
  its marginals are those of a variance-exploding diffusion in sigma, whose probability-flow ODE dx/dsigma = eps
  integrated by Euler from sigma_t to sigma_prev is exactly this step; one step from t = 999 is the network's own
  x0 prediction.
* :func:`sde_dpmsolver_pp` (``sampler: dpm-solver++``): what LiDiff and ScoreLiDAR run, diffusers 0.18's
  ``DPMSolverMultistepScheduler(algorithm_type="sde-dpmsolver++", solver_order=2, lower_order_final=True)`` with
  its "linspace" timesteps (n = 4: 999, 749, 500, 250) and its last step going to t = 0 (not to x0), applied to the
  offset x - x_init. Its formulas are the variance-*preserving* ones (x_t = alpha_t x_0 + sigma_t eps,
  x0_hat = (x_t - sigma_t eps_hat) / alpha_t), which the local-noise training never saw: they rescale the offset by
  1 / alpha_t (5.8x at t = 999), and a step to t = 0 adds SDE noise of sigma_0 = 6 mm. Kept for parity with
  released teachers.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

EpsFn = Callable[[Tensor, int], Tensor]  # eps_hat(x_t, t) for an integer timestep t


def _checked(eps: Tensor, i: int, t: int, n: int) -> Tensor:
    """``eps`` if finite, else a clear error (a diverged model; the kNN of the next step would fail obscurely)."""
    if not bool(torch.isfinite(eps).all()):
        from distilkit.errors import NonFiniteLossError

        raise NonFiniteLossError(f"sampling: the network's noise prediction became non-finite at step {i + 1} of {n} "
                                 f"(t = {t}): the model's weights have diverged")
    return eps


def ddim_timesteps(steps: int, diffusion_steps: int) -> list[int]:
    """``steps`` distinct timesteps, "trailing" spacing: round(T (n - i) / n) - 1 for i = 0 .. n - 1 (never 0
    unless n = T)."""
    if not 1 <= steps <= diffusion_steps:
        raise ValueError(f"sampler steps must lie in 1 .. {diffusion_steps}, got {steps}")
    return [int(round(diffusion_steps * (steps - i) / steps)) - 1 for i in range(steps)]


def ddim(eps_fn: EpsFn, x: Tensor, sigmas: Tensor, timesteps: list[int]) -> Tensor:
    """Deterministic DDIM of the local-noise process from x = x_T: one ``eps_fn`` call per timestep; returns x0_hat
    of the last one. ``sigmas`` (T,) holds sqrt(1 - abar_t)."""
    for i, t in enumerate(timesteps):
        eps = _checked(eps_fn(x, t), i, t, len(timesteps))
        x0 = x - sigmas[t].to(x.dtype) * eps
        x = x0 if i + 1 == len(timesteps) else x0 + sigmas[timesteps[i + 1]].to(x.dtype) * eps
    return x


def dpm_timesteps(steps: int, diffusion_steps: int) -> list[int]:
    """diffusers 0.18's timesteps: linspace(0, T - 1, n + 1) rounded, reversed, the last (0) dropped, duplicates
    removed in order."""
    if not 1 <= steps <= diffusion_steps:
        raise ValueError(f"sampler steps must lie in 1 .. {diffusion_steps}, got {steps}")
    values = torch.linspace(0, diffusion_steps - 1, steps + 1, dtype=torch.float64).round().long().tolist()[::-1][:-1]
    out: list[int] = []
    for v in values:
        if v not in out:
            out.append(int(v))
    return out


def sde_dpmsolver_pp(eps_fn: EpsFn, x: Tensor, alphas_cumprod: Tensor, timesteps: list[int],
                     generator: torch.Generator | None = None, lower_order_final: bool = True) -> Tensor:
    """Second-order multistep SDE-DPM-Solver++ (midpoint) from x at ``timesteps[0]``, as diffusers 0.18 steps it:
    per step one ``eps_fn`` call, x0_hat = (x - sigma_s eps_hat) / alpha_s, then one N(0, I) draw from
    ``generator``; first order at the first step (and at the last one when there are fewer than 15), the last step
    going to t = 0. With h = lambda_t - lambda_s (lambda = log alpha - log sigma):

        first order:  x_t = sigma_t / sigma_s e^-h x + alpha_t (1 - e^-2h) D0 + sigma_t sqrt(1 - e^-2h) z
        second order: the same plus 0.5 alpha_t (1 - e^-2h) D1, D1 = (D0 - D0_prev) h / h_prev.
    """
    abar = alphas_cumprod.double()
    alpha, sigma = abar.sqrt(), (1.0 - abar).sqrt()
    lam = alpha.log() - sigma.log()
    n = len(timesteps)
    previous: tuple[int, Tensor] | None = None  # (its timestep, its x0_hat)
    for i, s in enumerate(timesteps):
        t = timesteps[i + 1] if i + 1 < n else 0
        eps = _checked(eps_fn(x, s), i, s, n)
        d0 = (x - sigma[s].to(x.dtype) * eps) / alpha[s].to(x.dtype)
        z = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
        h = lam[t] - lam[s]
        decay = torch.exp(-2.0 * h)
        x_new = ((sigma[t] / sigma[s] * torch.exp(-h)).to(x.dtype) * x
                 + (alpha[t] * (1.0 - decay)).to(x.dtype) * d0
                 + (sigma[t] * (1.0 - decay).sqrt()).to(x.dtype) * z)
        last_low = lower_order_final and i == n - 1 and n < 15
        if previous is not None and not last_low:
            s1, d0_prev = previous
            r0 = (lam[s] - lam[s1]) / h
            x_new = x_new + (0.5 * alpha[t] * (1.0 - decay) / r0).to(x.dtype) * (d0 - d0_prev)
        previous = (s, d0)
        x = x_new
    return x


__all__ = ["ddim", "ddim_timesteps", "dpm_timesteps", "sde_dpmsolver_pp"]
