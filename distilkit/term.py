"""The term contract shared by task losses and distillation objectives: one protocol for one idea.

A term declares its **roles** and where each comes from:

* a student tap — a role in ``CONSUMES`` (role -> tap kind) that is not a teacher role;
* a teacher tap — a role in ``CONSUMES`` that is also in ``TEACHER_ROLES``;
* a batch field — a role in ``BATCH`` (role -> field of :class:`~distilkit.data.batch.Batch`, e.g.
  ``voxel_target``; ``validate`` checks the data provides it, a recipe may name another field);
* a teacher capability — a method of the teacher's adapter named in ``REQUIRES`` (e.g. ``denoise``),
  reached through :attr:`Term.context`.

The trainer resolves every role before calling :meth:`Term.compute` with a dict role -> value, so a term
never reads model outputs or the batch by name. The lifecycle, for every term: :meth:`Term.prepare` (training
split statistics), :meth:`Term.setup` (first batch, to size own layers), :meth:`Term.bind`, then per step
:meth:`Term.compute` and, after the student's optimizer step, :meth:`Term.update`. A term's parameters train with
the student unless :meth:`Term.own_optimizer` returns an optimizer (own learning rate and clipping, stepped in
:meth:`Term.update`, checkpointed with the stage).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

import torch
from pydantic import BaseModel
from torch import Tensor, nn

from distilkit.cards.base import TermCard
from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX, NUM_CLASSES
from distilkit.data.info import DataInfo


@dataclass
class TermContext:
    """What a term may reach beyond its roles: the frozen teacher (and its capabilities, e.g. ``denoise``),
    the student, the device and the data's facts (``info``: class table with its ignore index, grid, cameras).
    Bound once, before training. A term that steps its own optimizer calls
    ``sync(params)`` between its backward pass and the step: in multi-process training it averages those
    gradients over the processes (a no-op in one process)."""

    student: nn.Module
    teacher: nn.Module | None
    device: torch.device
    sync: Callable[[Iterable[nn.Parameter]], None] = field(default=lambda params: None)
    info: DataInfo | None = None


class Term(TermCard, nn.Module, ABC):
    """A weighted scalar term of a stage's loss (see the module docstring for the roles and lifecycle; its
    declarations are :class:`~distilkit.cards.base.TermCard`'s)."""

    def __init__(self, params: BaseModel) -> None:
        super().__init__()
        self.params = params
        #: what the trainer binds (:meth:`bind`): the data's facts, the teacher's adapter, the device
        self.context: TermContext | None = None

    def batch_roles(self, batch: Batch) -> dict[str, Any]:
        """Every batch role's value from ``batch`` by its default field (calling a term outside a stage)."""
        present = batch.fields | frozenset(batch.meta)
        return {role: batch.field(self.default_field(role, present)) for role in self.BATCH}

    def prepare(self, train_set: Any) -> None:
        """Statistics of the training split the term needs (e.g. class weights); default: none."""

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        """Build shape-dependent layers from one batch's role values (default: nothing to build)."""

    def bind(self, context: TermContext) -> None:
        """Keep the trainer's ``context`` (:attr:`context`), once, before the first step."""
        self.context = context

    @property
    def num_classes(self) -> int:
        """The data's class count (its class table's; SemanticKITTI's 20 before binding)."""
        info = self.context.info if self.context is not None else None
        return info.num_classes if info is not None else NUM_CLASSES

    @property
    def ignore_index(self) -> int:
        """The label the losses never use (the data's class table's; SemanticKITTI's 255 before binding)."""
        info = self.context.info if self.context is not None else None
        return info.classes.ignore_index if info is not None else IGNORE_INDEX

    def own_optimizer(self) -> torch.optim.Optimizer | None:
        """An optimizer for this term's own modules, stepped in :meth:`update` (default: none)."""
        return None

    @abstractmethod
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        """The scalar loss from the value of every role (taps and batch fields)."""

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        """Own optimisation after the student's step (e.g. a score network; may take several steps), with
        the batch and this term's role values, detached. Returns values to log."""
        return {}


__all__ = ["Term", "TermContext"]
