"""The optimizers' and learning-rate schedules' declarations (torch-free): their registrations and the schedules'
parameters; the factories and factor functions (:mod:`distilkit.engine.train.optim`) are imported when a stage
trains."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from distilkit.registry import OPTIMIZERS, SCHEDULES, NoParams

_IMPL = "distilkit.engine.train.optim"

OPTIMIZERS.declare("adam", f"{_IMPL}:_adam", card=None, description="Adam (lr, betas, weight_decay as L2)",
                   paper="Kingma & Ba, ICLR 2015")
OPTIMIZERS.declare("adamw", f"{_IMPL}:_adamw", card=None, description="AdamW (lr, betas, decoupled weight_decay)",
                   paper="Loshchilov & Hutter, ICLR 2019")
OPTIMIZERS.declare("sgd", f"{_IMPL}:_sgd", card=None, description="SGD with momentum (lr, momentum, weight_decay)",
                   paper="—")


class StepParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    step_size: int = Field(..., ge=1, description="steps between decays")
    gamma: float = Field(0.1, gt=0, le=1, description="factor per decay (JS3C-Net: 0.7 every 5 epochs)")


class CosineParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    min_factor: float = Field(0.0, ge=0, le=1, description="the factor reached at the last step")


SCHEDULES.declare("constant", f"{_IMPL}:constant", card=None, description="the optimizer's learning rate throughout",
                  paper="—", params=NoParams)
SCHEDULES.declare("step", f"{_IMPL}:step_decay", card=None, description="multiply by gamma every step_size steps",
                  paper="—", params=StepParams)
SCHEDULES.declare("cosine", f"{_IMPL}:cosine", card=None, description="cosine decay to min_factor at the last step",
                  paper="Loshchilov & Hutter, ICLR 2017 (SGDR)", params=CosineParams)

__all__ = ["CosineParams", "NoParams", "StepParams"]
