"""VSD score distillation (ScoreLiDAR §4.1, eq. 7-11) with an auxiliary score network of the student's samples."""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.data.batch import Batch
from distilkit.losses.vsd import vsd
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.lora import full_copy, lora_copy
from distilkit.structures import PointCloud


class VSDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    aux: Literal["lora", "copy"] = Field("lora", description="the auxiliary score network: a LoRA of the teacher's "
                                                            "denoiser (the paper) or a full copy (the released code)")
    rank: int = Field(8, ge=1, description="LoRA rank")
    aux_lr: float = Field(3e-5, gt=0, description="learning rate of the auxiliary network (ScoreLiDAR: SGD 3e-5)")
    aux_optimizer: Literal["sgd", "adam"] = "sgd"
    aux_steps: int = Field(1, ge=1, description="auxiliary steps per student step (ScoreLiDAR: 1, alternating)")
    aux_grad_clip: float | None = Field(None, gt=0, description="gradient clipping of the auxiliary network")
    t_min: int = Field(0, ge=0, description="re-noising timesteps t ~ U{t_min .. t_max} (ScoreLiDAR: 0 .. 999)")
    t_max: int | None = Field(None, ge=0, description="(default: T - 1)")
    weighting: Literal["uniform", "sigma"] = Field(
        "uniform", description="w(t): 1 (eq. 11 as written) or sigma_t = sqrt(1 - abar_t)")


class VSD(MultiTapObjective):
    """Variational score distillation for a few-step point generator (ScoreLiDAR eq. 9-11).

    Each step: t ~ U{t_min..t_max}, eps ~ N(0, I), the student's samples re-noised with LiDiff's local noise
    x_t = x0 + sigma_t eps; the frozen teacher's and the auxiliary network's noise predictions at x_t (both
    conditional, no guidance, no gradient); the loss :func:`distilkit.losses.vsd` whose gradient is
    w(t) (eps_teacher - eps_aux) / numel. After the student's step, the auxiliary network (a LoRA of the teacher's
    denoiser, or a copy) takes ``aux_steps`` denoising steps (eq. 5) on the detached samples with its own optimizer.
    The teacher must offer ``predict_noise(x_t, t, condition)`` and ``alphas_cumprod``.
    """

    Params = VSDParams
    CONSUMES = {"student": "points"}
    TEACHER_ROLES = frozenset()
    BATCH = {"condition": "scan"}
    REQUIRES = frozenset({"predict_noise"})
    DEFAULT_WEIGHT = 1.0

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        assert self.context is not None and self.context.teacher is not None, "bound to a teacher before setup"
        teacher = self.context.teacher
        self.aux = lora_copy(teacher, self.params.rank) if self.params.aux == "lora" else full_copy(teacher)
        self.aux.train()

    def own_optimizer(self) -> torch.optim.Optimizer:
        params = [p for p in self.aux.parameters() if p.requires_grad]
        if self.params.aux_optimizer == "sgd":
            self.opt = torch.optim.SGD(params, lr=self.params.aux_lr)
        else:
            self.opt = torch.optim.Adam(params, lr=self.params.aux_lr)
        return self.opt

    def _noised(self, x0: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        teacher = self.context.teacher  # type: ignore[union-attr]
        abar = teacher.alphas_cumprod
        top = len(abar) - 1 if self.params.t_max is None else min(self.params.t_max, len(abar) - 1)
        t = torch.randint(min(self.params.t_min, top), top + 1, (x0.shape[0],), device=x0.device)
        sigma = (1.0 - abar[t]).sqrt()[:, None, None].to(x0.dtype)
        eps = torch.randn_like(x0)
        return x0 + sigma * eps, t, eps

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        samples: PointCloud = taps["student"]
        x0 = samples.points
        with torch.no_grad():
            x_t, t, _ = self._noised(x0.detach())
            eps_teacher = self.context.teacher.predict_noise(x_t, t, taps["condition"])  # type: ignore[union-attr]
            eps_aux = self.aux.predict_noise(x_t, t, taps["condition"])
        weight: float | Tensor = 1.0
        if self.params.weighting == "sigma":
            weight = (1.0 - self.context.teacher.alphas_cumprod[t]).sqrt()[:, None, None]  # type: ignore[union-attr]
        return vsd(x0, eps_teacher, eps_aux, weight)

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        x0 = taps["student"].points.detach()
        values = []
        for _ in range(self.params.aux_steps):
            x_t, t, eps = self._noised(x0)
            loss = nn.functional.mse_loss(self.aux.predict_noise(x_t, t, taps["condition"]), eps)  # eq. 5
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            self.context.sync(p for p in self.aux.parameters() if p.requires_grad)
            if self.params.aux_grad_clip is not None:
                nn.utils.clip_grad_norm_([p for p in self.aux.parameters() if p.requires_grad], self.params.aux_grad_clip)
            self.opt.step()
            values.append(float(loss.detach()))
        return {"vsd_aux_loss": sum(values) / len(values)}


register_objective("vsd", VSD, description="variational score distillation with an auxiliary (LoRA) score network "
                                           "trained on the student's samples",
                   paper="ScoreLiDAR (Zhang et al., ICCV 2025), eq. 7-11; ProlificDreamer's VSD",
                   equation="∇ = w(t) (ε_teacher(x_t, t, c) − ε_aux(x_t, t, c)) ∂x0/∂θ, x_t = x0 + σ_t ε; ε_aux trained "
                            "with eq. 5 on sg(x0), 1:1",
                   shapes="student samples: points (B, M, 3); condition: the batch's scan; teacher: predict_noise")
