"""The objective contract: a registered :class:`~distilkit.term.Term` around a loss of :mod:`distilkit.losses`."""

from __future__ import annotations

from abc import abstractmethod
from typing import Any

from torch import Tensor

from distilkit.cards.base import ObjectiveCard
from distilkit.data.batch import Batch
from distilkit.term import Term, TermContext


class Objective(ObjectiveCard, Term):
    """A distillation term (:class:`~distilkit.term.Term`) whose ``teacher`` role reads the teacher.

    Roles in ``TEACHER_ROLES`` read the teacher's outputs, the others the student's (the teacher runs only
    when some term reads one of its taps). ``REQUIRES`` names teacher capabilities (methods of its adapter,
    e.g. ``denoise``) the objective calls through ``self.context``; ``validate`` checks that the teacher has
    them. A two-role objective implements ``forward(student, teacher, batch)``.
    """

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The loss from the taps of every role (default: ``forward(student, teacher, batch)``)."""
        return self(taps["student"], taps["teacher"], batch)

    @abstractmethod
    def forward(self, student: Any, teacher: Any, batch: Batch) -> Tensor:
        """The scalar distillation loss between the student's and the teacher's taps."""


class MultiTapObjective(Objective):
    """An objective that reads more roles than ``student``/``teacher`` (taps or batch fields): it implements
    :meth:`compute`; calling it with two taps and a batch is ``compute`` with its batch roles read from the batch by
    their default fields."""

    @abstractmethod
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The loss from the taps of every role."""

    def forward(self, student: Any, teacher: Any, batch: Batch) -> Tensor:
        return self.compute({"student": student, "teacher": teacher, **self.batch_roles(batch)}, batch)


def register_objective(name: str, cls: type[Objective], *, description: str, paper: str, equation: str,
                       shapes: str, function: str | None = None) -> type[Objective]:
    """Register ``cls`` under ``name``; tap kinds and the default weight are read from the class. ``function``:
    the plain function of ``distilkit.losses`` that computes its maths (default: ``name``)."""
    from distilkit.registry import OBJECTIVES

    kinds = tuple(dict.fromkeys(cls.CONSUMES.values()))
    return OBJECTIVES.add(name, cls, description=description, paper=paper, consumes=kinds,
                          default_weight=cls.DEFAULT_WEIGHT, equation=equation, shapes=shapes,
                          function=f"distilkit.losses.{function or name}")


__all__ = ["MultiTapObjective", "Objective", "TermContext", "register_objective"]
