"""Registered distillation objectives (nn.Module wrappers around :mod:`distilkit.losses`)."""

from distilkit.objectives.base import Objective
from distilkit.objectives import connectors as _connectors  # noqa: F401  (registers the connectors)
from distilkit.objectives import dpo as _dpo  # noqa: F401  (registers the objectives)
from distilkit.objectives import dskd as _dskd  # noqa: F401
from distilkit.objectives import feature as _feature  # noqa: F401
from distilkit.objectives import hassc as _hassc  # noqa: F401
from distilkit.objectives import l2cocc as _l2cocc  # noqa: F401
from distilkit.objectives import logit as _logit  # noqa: F401
from distilkit.objectives import region as _region  # noqa: F401
from distilkit.objectives import relational as _relational  # noqa: F401
from distilkit.objectives import score as _score  # noqa: F401
from distilkit.objectives import structural as _structural  # noqa: F401

__all__ = ["Objective"]
