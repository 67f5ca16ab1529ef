"""The objective contract: a registered ``nn.Module`` around a loss of :mod:`distilkit.losses`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from pydantic import BaseModel
from torch import Tensor, nn


class Objective(nn.Module, ABC):
    """A distillation term ``forward(student_tap, teacher_tap, batch) -> scalar``.

    ``CONSUMES`` maps the roles ``student`` and ``teacher`` to the tap kind each needs;
    ``DEFAULT_WEIGHT`` is the weight for this field when a recipe gives none. Trainable
    parameters of an objective are optimised with the student and saved in its checkpoint.
    """

    Params: ClassVar[type[BaseModel]]
    CONSUMES: ClassVar[dict[str, str]] = {}
    DEFAULT_WEIGHT: ClassVar[float] = 1.0

    def __init__(self, params: BaseModel) -> None:
        super().__init__()
        self.params = params

    @abstractmethod
    def forward(self, student: Any, teacher: Any, batch: dict[str, Tensor]) -> Tensor:
        """The scalar distillation loss between the student's and the teacher's taps."""

    def update(self, step: int) -> dict[str, float]:
        """Own optimisation after the student's step (e.g. a score network); returns logged values."""
        return {}
