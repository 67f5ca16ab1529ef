"""The inputs that a stage's frozen auxiliary models give (``aux:`` in a recipe: Scribble2Scene's query proposals),
added to a batch before the student and the teacher read it."""

from __future__ import annotations

from typing import Any

import torch


def with_aux_inputs(batch: Any, aux: list[tuple[Any, Any]], training: bool = False) -> Any:
    """``batch`` with the inputs the frozen auxiliary models give: each (resolved aux, model)'s taps under no_grad
    (for a ``training`` batch, only those of the auxiliary models that run in training)."""
    aux = [(spec, model) for spec, model in aux if spec.training or not training]
    if not aux:
        return batch
    added: dict[str, Any] = {}
    with torch.no_grad():
        for spec, model in aux:
            out = model(batch)
            added.update({field: out[tap] for tap, field in spec.inputs.items()})
    return batch.with_inputs(**added)


__all__ = ["with_aux_inputs"]
