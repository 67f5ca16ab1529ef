"""Card of VSD score distillation, ScoreLiDAR §4.1 (:mod:`distilkit.objectives.score`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import ObjectiveCard, declare_objective


class VSDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    aux: Literal["copy", "lora"] = Field(
        "copy", description="the auxiliary score network: a full copy of the teacher initialised from it (ScoreLiDAR "
                            "appendix A.3 and its released code; default) or a LoRA of the teacher's denoiser "
                            "(distilkit's cheaper option: §4.1 names LoRA as one possible parametrisation, as "
                            "ProlificDreamer does, but neither the paper's experiments nor the code use one)")
    rank: int = Field(8, ge=1, description="LoRA rank with aux: lora (no source gives one: 8 and the scale alpha / "
                                           "rank = 1 are distilkit's)")
    aux_lr: float = Field(3e-5, gt=0, description="learning rate of the auxiliary network (ScoreLiDAR: SGD 3e-5)")
    aux_optimizer: Literal["sgd", "adam"] = "sgd"
    aux_steps: int = Field(1, ge=1, description="auxiliary steps per student step (ScoreLiDAR: 1, alternating)")
    aux_grad_clip: float | None = Field(None, gt=0, description="gradient clipping of the auxiliary network")
    t_min: int = Field(0, ge=0, description="re-noising timesteps t ~ U{t_min .. t_max} (ScoreLiDAR: 0 .. 999)")
    t_max: int | None = Field(None, ge=0, description="(default: T - 1)")
    weighting: Literal["uniform", "sigma"] = Field(
        "uniform", description="w(t): 1 (eq. 11 as written) or sigma_t = sqrt(1 - abar_t)")
    aux_update: Literal["before", "after"] = Field(
        "before", description="the auxiliary network's steps come before the student's (the released code: optimizer "
                              "0 then 1 on every batch, so the first student step already sees a fitted network) or "
                              "after it")
    aux_sample: Literal["fresh", "same"] = Field(
        "fresh", description="what the auxiliary network fits: a fresh sample of the student from new noise, drawn "
                             "without gradient (the released code: its aux step generates its own samples; needs the "
                             "student's generate) or the very samples it is then queried on")


class VSDCard(ObjectiveCard):
    """Variational score distillation (card of :class:`distilkit.objectives.score.VSD`): the teacher's
    ``predict_noise``, and the student's ``generate`` for a fresh auxiliary sample."""

    Params = VSDParams
    TAP_HINTS = {"student": ("samples",)}  # LiDiff's first points tap is eps_pred
    CONSUMES = {"student": "points"}
    TEACHER_ROLES = frozenset()
    BATCH = {"condition": "scan"}
    REQUIRES = frozenset({"predict_noise"})
    DEFAULT_WEIGHT = 1.0
    VERSION = 2  # 2: a full copy as the auxiliary network, fitted on a fresh student sample (the released code)

    @classmethod
    def student_requires(cls, params: BaseModel) -> frozenset[str]:
        """``generate`` for a fresh auxiliary sample, beside what the class always calls."""
        fresh = frozenset({"generate"}) if getattr(params, "aux_sample") == "fresh" else frozenset()
        return cls.STUDENT_REQUIRES | fresh


declare_objective("vsd", "distilkit.objectives.score:VSD", VSDCard,
                  description="variational score distillation with an auxiliary score network (a copy of the "
                              "teacher, or a LoRA) trained on the student's samples",
                  paper="ScoreLiDAR (Zhang et al., ICCV 2025), eq. 7-11; ProlificDreamer's VSD",
                  equation="∇ = w(t) (ε_teacher(x_t, t, c) − ε_aux(x_t, t, c)) ∂x0/∂θ, x_t = x0 + σ_t ε; ε_aux trained "
                           "with eq. 5 on a fresh student sample, 1:1, before the student's step",
                  shapes="student samples: points (B, M, 3); condition: the batch's scan; teacher: predict_noise")

__all__ = ["VSDCard", "VSDParams"]
