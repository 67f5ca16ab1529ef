"""The objective contract: a registered ``nn.Module`` around a loss of :mod:`distilkit.losses`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from pydantic import BaseModel
from torch import Tensor, nn

from distilkit.data.batch import Batch


@dataclass
class TermContext:
    """What an objective may reach beyond its taps: the frozen teacher (and its capabilities, e.g.
    ``denoise``), the student, and the device. Bound once, before training."""

    student: nn.Module
    teacher: nn.Module | None
    device: torch.device


class Objective(nn.Module, ABC):
    """A distillation term.

    ``CONSUMES`` maps roles to the tap kind each needs; roles in ``TEACHER_ROLES`` read the teacher's
    outputs, the others the student's (the teacher runs only when some term reads one of its taps).
    Roles in ``OPTIONAL`` are used only when the recipe names a tap for them. ``REQUIRES`` names teacher
    capabilities (methods of its adapter, e.g. ``denoise``) the objective calls through ``self.context``;
    ``validate`` checks that the teacher has them. The trainer calls :meth:`setup` once with the taps of a
    first batch (to size own layers), binds the context, then calls :meth:`compute` every step and
    :meth:`update` after each student step.

    Trainable parameters are optimised with the student and saved in its checkpoint, unless
    :meth:`own_optimizer` returns an optimizer: then the objective trains them itself in :meth:`update`
    (own learning rate and clipping, excluded from the student's), and the optimizer's state is saved
    with the stage. ``DEFAULT_WEIGHT`` is the weight when a recipe gives none.
    """

    Params: ClassVar[type[BaseModel]]
    CONSUMES: ClassVar[dict[str, str]] = {}
    TEACHER_ROLES: ClassVar[frozenset[str]] = frozenset({"teacher"})
    OPTIONAL: ClassVar[frozenset[str]] = frozenset()
    REQUIRES: ClassVar[frozenset[str]] = frozenset()
    DEFAULT_WEIGHT: ClassVar[float] = 1.0
    DEFAULT_CONNECTOR: ClassVar[str | None] = None  # e.g. "linear": the student tap is projected first
    VERSION: ClassVar[int] = 1  # bump when the objective's numbers change: stages using it retrain

    def __init__(self, params: BaseModel) -> None:
        super().__init__()
        self.params = params
        self.context: TermContext | None = None

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        """Build shape-dependent layers from one batch's taps (default: nothing to build)."""

    def bind(self, context: TermContext) -> None:
        self.context = context

    def own_optimizer(self) -> torch.optim.Optimizer | None:
        """An optimizer for this objective's own modules, stepped in :meth:`update` (default: none)."""
        return None

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The loss from the taps of every role (default: ``forward(student, teacher, batch)``)."""
        return self(taps["student"], taps["teacher"], batch)

    @abstractmethod
    def forward(self, student: Any, teacher: Any, batch: Batch) -> Tensor:
        """The scalar distillation loss between the student's and the teacher's taps."""

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        """Own optimisation after the student's step (e.g. a score network; may take several steps), with
        the batch and this objective's taps, detached. Returns values to log."""
        return {}


class MultiTapObjective(Objective):
    """An objective that reads more roles than ``student``/``teacher``: it implements :meth:`compute`;
    calling it with two taps is the same as ``compute({"student": ..., "teacher": ...})``."""

    @abstractmethod
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The loss from the taps of every role."""

    def forward(self, student: Any, teacher: Any, batch: Batch) -> Tensor:
        return self.compute({"student": student, "teacher": teacher}, batch)


def register_objective(name: str, cls: type[Objective], *, description: str, paper: str, equation: str,
                       shapes: str) -> type[Objective]:
    """Register ``cls`` under ``name``; tap kinds and the default weight are read from the class."""
    from distilkit.registry import OBJECTIVES

    kinds = tuple(dict.fromkeys(cls.CONSUMES.values()))
    return OBJECTIVES.add(name, cls, description=description, paper=paper, consumes=kinds,
                          default_weight=cls.DEFAULT_WEIGHT, equation=equation, shapes=shapes)
