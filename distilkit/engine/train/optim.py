"""Registered optimizers and learning-rate schedules (``optimizer: {name, schedule: {name, params, warmup_steps}}``
in a recipe); plugins add their own with ``OPTIMIZERS.add`` / ``SCHEDULES.add``. The built-in ones are declared
(with the schedules' parameters) in :mod:`distilkit.cards.optim`; this module holds what runs.

An optimizer is ``factory(param_groups, spec) -> torch.optim.Optimizer`` (``spec``: the recipe's optimizer
section). A schedule is ``factor(step, total, params) -> float``, the multiplier of every group's learning rate at
0-based ``step`` of ``total``; it is a pure function of the step, so a resumed run continues it exactly (nothing to
checkpoint). A linear warm-up (``warmup_steps``) multiplies any schedule by ``(step + 1) / warmup_steps`` until it
ends (Goyal et al. 2017).
"""

from __future__ import annotations

import math
from typing import Any

import torch
from pydantic import BaseModel

from distilkit.cards.optim import CosineParams, StepParams
from distilkit.registry import SCHEDULES, NoParams


def _adam(groups: list[dict[str, Any]], spec: Any) -> torch.optim.Optimizer:
    return torch.optim.Adam(groups, lr=spec.lr, betas=spec.betas, weight_decay=spec.weight_decay)


def _adamw(groups: list[dict[str, Any]], spec: Any) -> torch.optim.Optimizer:
    return torch.optim.AdamW(groups, lr=spec.lr, betas=spec.betas, weight_decay=spec.weight_decay)


def _sgd(groups: list[dict[str, Any]], spec: Any) -> torch.optim.Optimizer:
    return torch.optim.SGD(groups, lr=spec.lr, momentum=spec.momentum, weight_decay=spec.weight_decay)


def constant(step: int, total: int, params: BaseModel) -> float:
    return 1.0


def step_decay(step: int, total: int, params: BaseModel) -> float:
    """``gamma ** (step // step_size)``."""
    assert isinstance(params, StepParams)
    return params.gamma ** (step // params.step_size)


def cosine(step: int, total: int, params: BaseModel) -> float:
    """``min + (1 - min) (1 + cos(pi step / total)) / 2`` (Loshchilov & Hutter, SGDR, without restarts)."""
    assert isinstance(params, CosineParams)
    progress = min(step / max(total, 1), 1.0)
    return params.min_factor + (1.0 - params.min_factor) * 0.5 * (1.0 + math.cos(math.pi * progress))


def lr_factor(schedule: Any, params: BaseModel, step: int, total: int) -> float:
    """The learning-rate multiplier at 0-based ``step``: the schedule's factor times the linear warm-up's."""
    factor = SCHEDULES.get(schedule.name)(step, total, params)
    if schedule.warmup_steps and step < schedule.warmup_steps:
        factor *= (step + 1) / schedule.warmup_steps
    return factor


def weight_factor(warmup_steps: int, step: int) -> float:
    """A loss term's weight multiplier at 0-based ``step`` under a linear warm-up of ``warmup_steps`` (mdistiller
    warms the distillation weight up over the first epochs; 0: none)."""
    return 1.0 if not warmup_steps else min(1.0, (step + 1) / warmup_steps)


__all__ = ["CosineParams", "NoParams", "StepParams", "constant", "cosine", "lr_factor", "step_decay", "weight_factor"]
