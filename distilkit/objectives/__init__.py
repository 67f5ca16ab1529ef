"""Registered distillation objectives (nn.Module wrappers around :mod:`distilkit.losses`)."""

from distilkit.objectives.base import Objective
from distilkit.objectives import dskd as _dskd  # noqa: F401  (registers "dskd")

__all__ = ["Objective"]
