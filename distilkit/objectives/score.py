"""VSD score distillation (ScoreLiDAR §4.1, eq. 7-11) with an auxiliary score network of the student's samples."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.objectives.score import VSDCard, VSDParams
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.vsd import vsd
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.lora import full_copy, lora_copy


class VSD(VSDCard, MultiTapObjective):
    """Variational score distillation for a few-step point generator (ScoreLiDAR eq. 9-11).

    Each step: t ~ U{t_min..t_max}, eps ~ N(0, I), the student's samples re-noised with LiDiff's local noise
    x_t = x0 + sigma_t eps; the frozen teacher's and the auxiliary network's noise predictions at x_t (both
    conditional, no guidance, no gradient); the loss :func:`distilkit.losses.vsd` whose gradient is
    w(t) (eps_teacher - eps_aux) / numel. Before the student's step (``aux_update``; or after it), the auxiliary
    network takes ``aux_steps`` denoising steps (eq. 5) with its own optimizer on a fresh sample of the student
    (``aux_sample``: generated from new noise without gradient, as the released code's aux step does; or on the
    detached samples themselves). The auxiliary network is a full copy of the teacher initialised from it
    (appendix A.3, the released code) unless ``aux: lora`` (distilkit's option). The teacher must offer
    ``predict_noise(x_t, t, condition)`` and ``alphas_cumprod``; a fresh sample needs the student's ``generate``.
    """

    CHOICES = (
        Choice("auxiliary score network", "a full copy of the teacher, initialised from it",
               "§4.1: a small U-Net or a LoRA of the teacher; appendix A.3: the teacher's architecture, initialised "
               "from it", "three full copies (generator, teacher, auxDiff)", "`aux: lora` (`rank`)"),
        Choice("what the auxiliary network fits", "a fresh student sample from new noise, without gradient",
               "the student's generated samples (eq. 5)", "its aux step generates its own samples",
               "`aux_sample: same`"),
        Choice("the VSD gradient", "w(t)(eps_teacher - eps_aux) through the samples (eq. 11)", "eq. 11",
               "((eps_teacher - eps_aux)(x_t - x_0)).mean(): exactly zero gradient (x_t - x_0 does not depend on the samples)"),
    )

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        assert self.context is not None and self.context.teacher is not None, "bound to a teacher before setup"
        self.aux = self._aux_copy()
        self._aux_losses: list[float] = []

    def _aux_copy(self) -> nn.Module:
        teacher = self.context.teacher  # type: ignore[union-attr]
        aux = lora_copy(teacher, self.params.rank) if self.params.aux == "lora" else full_copy(teacher)
        return aux.train()

    def aux_networks(self) -> list[nn.Module]:
        """The auxiliary score networks this objective trains (VSD: one)."""
        return [self.aux]

    def own_optimizer(self) -> torch.optim.Optimizer:
        groups = [{"params": [p for p in net.parameters() if p.requires_grad]} for net in self.aux_networks()]
        if self.params.aux_optimizer == "sgd":
            self.opt = torch.optim.SGD(groups, lr=self.params.aux_lr)
        else:
            self.opt = torch.optim.Adam(groups, lr=self.params.aux_lr)
        return self.opt

    def _noised(self, x0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        teacher = self.context.teacher  # type: ignore[union-attr]
        abar = teacher.alphas_cumprod
        top = len(abar) - 1 if self.params.t_max is None else min(self.params.t_max, len(abar) - 1)
        t = torch.randint(min(self.params.t_min, top), top + 1, (x0.shape[0],), device=x0.device)
        sigma = (1.0 - abar[t]).sqrt()[:, None, None].to(x0.dtype)
        eps = torch.randn_like(x0)
        return x0 + sigma * eps, t, eps

    def _weight(self, t: Tensor) -> float | Tensor:
        if self.params.weighting == "sigma":
            return (1.0 - self.context.teacher.alphas_cumprod[t]).sqrt()[:, None, None]  # type: ignore[union-attr]
        return 1.0

    def _predictions(self, aux: nn.Module, x0: Tensor, condition: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(eps_teacher, eps_aux, t) at x0 re-noised, no gradient."""
        with torch.no_grad():
            x_t, t, _ = self._noised(x0.detach())
            eps_teacher = self.context.teacher.predict_noise(x_t, t, condition)  # type: ignore[union-attr]
            return eps_teacher, aux.predict_noise(x_t, t, condition), t

    def fresh(self, noise: Tensor, condition: Tensor) -> Tensor:
        """The student's sample from ``noise``, without gradient and in evaluation mode (the released code's aux
        step: ``generator.eval()`` under ``no_grad``)."""
        student = self.context.student  # type: ignore[union-attr]  (its generate(): checked by the recipe)
        was = student.training
        student.eval()
        try:
            with torch.no_grad():
                return student.generate(condition, noise)
        finally:
            student.train(was)

    def fit_aux(self, pairs: list[tuple[nn.Module, Tensor]], condition: Tensor) -> None:
        """``aux_steps`` denoising steps (eq. 5) of each auxiliary network on its detached samples, one optimizer
        step for all of them."""
        for _ in range(self.params.aux_steps):
            self.opt.zero_grad(set_to_none=True)
            total = 0.0
            for aux, x0 in pairs:
                x_t, t, eps = self._noised(x0.detach())
                loss = nn.functional.mse_loss(aux.predict_noise(x_t, t, condition), eps)
                loss.backward()
                total += float(loss.detach())
            params = [p for net in self.aux_networks() for p in net.parameters() if p.requires_grad]
            self.context.sync(params)  # type: ignore[union-attr]
            if self.params.aux_grad_clip is not None:
                nn.utils.clip_grad_norm_(params, self.params.aux_grad_clip)
            self.opt.step()
            self._aux_losses.append(total / len(pairs))

    def aux_samples(self, x0: Tensor, condition: Tensor) -> Tensor:
        """What the auxiliary network fits this step (``aux_sample``)."""
        return self.fresh(torch.randn_like(x0), condition) if self.params.aux_sample == "fresh" else x0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        x0 = taps["student"].points
        if self.params.aux_update == "before":
            self.fit_aux([(self.aux, self.aux_samples(x0, taps["condition"]))], taps["condition"])
        eps_teacher, eps_aux, t = self._predictions(self.aux, x0, taps["condition"])
        return vsd(x0, eps_teacher, eps_aux, self._weight(t))

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        if self.params.aux_update == "after":
            x0 = taps["student"].points
            self.fit_aux([(self.aux, self.aux_samples(x0, taps["condition"]))], taps["condition"])
        values, self._aux_losses = self._aux_losses, []
        return {"vsd_aux_loss": sum(values) / len(values)} if values else {}


__all__ = ["VSD", "VSDParams"]
