"""Distillation objectives (nn.Module wrappers around :mod:`distilkit.losses`) and connectors. Their cards,
declared in :mod:`distilkit.cards.objectives` and :mod:`distilkit.cards.connectors`, register them; a module here is
imported the first time its objective runs."""

from distilkit.objectives.base import Objective

__all__ = ["Objective"]
