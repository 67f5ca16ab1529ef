"""The objective contract: a registered ``nn.Module`` around a loss of :mod:`distilkit.losses`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from pydantic import BaseModel
from torch import Tensor, nn
from distilkit.data.batch import Batch


class Objective(nn.Module, ABC):
    """A distillation term.

    ``CONSUMES`` maps roles to the tap kind each needs. Roles starting with ``teacher`` read the
    teacher's outputs, all others the student's; roles in ``OPTIONAL`` are used only when the
    recipe names a tap for them. The trainer calls :meth:`setup` once with the taps of a first
    batch (to size own layers, e.g. a regressor) before the optimizer is built, then
    :meth:`compute` every step. Trainable parameters are optimised with the student and saved in
    its checkpoint. ``DEFAULT_WEIGHT`` is the weight for this field when a recipe gives none.
    """

    Params: ClassVar[type[BaseModel]]
    CONSUMES: ClassVar[dict[str, str]] = {}
    OPTIONAL: ClassVar[frozenset[str]] = frozenset()
    DEFAULT_WEIGHT: ClassVar[float] = 1.0
    DEFAULT_CONNECTOR: ClassVar[str | None] = None  # e.g. "linear": the student tap is projected first
    VERSION: ClassVar[int] = 1  # bump when the objective's numbers change: stages using it retrain

    def __init__(self, params: BaseModel) -> None:
        super().__init__()
        self.params = params

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        """Build shape-dependent layers from one batch's taps (default: nothing to build)."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The loss from the taps of every role (default: ``forward(student, teacher, batch)``)."""
        return self(taps["student"], taps["teacher"], batch)

    @abstractmethod
    def forward(self, student: Any, teacher: Any, batch: Batch) -> Tensor:
        """The scalar distillation loss between the student's and the teacher's taps."""

    def update(self, step: int) -> dict[str, float]:
        """Own optimisation after the student's step (e.g. a score network); returns logged values."""
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
