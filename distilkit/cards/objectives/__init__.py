"""The distillation objectives' cards (torch-free): each one's parameters, roles and metadata, declared with
:func:`distilkit.cards.base.declare_objective`; the implementations live in :mod:`distilkit.objectives` and are
imported when an objective runs. Importing this package declares every built-in objective."""

from distilkit.cards.objectives import bev as _bev  # noqa: F401  (declares the objectives)
from distilkit.cards.objectives import dpo as _dpo  # noqa: F401
from distilkit.cards.objectives import dskd as _dskd  # noqa: F401
from distilkit.cards.objectives import feature as _feature  # noqa: F401
from distilkit.cards.objectives import hassc as _hassc  # noqa: F401
from distilkit.cards.objectives import l2cocc as _l2cocc  # noqa: F401
from distilkit.cards.objectives import licrocc as _licrocc  # noqa: F401
from distilkit.cards.objectives import logit as _logit  # noqa: F401
from distilkit.cards.objectives import monoocc as _monoocc  # noqa: F401
from distilkit.cards.objectives import region as _region  # noqa: F401
from distilkit.cards.objectives import relational as _relational  # noqa: F401
from distilkit.cards.objectives import score as _score  # noqa: F401
from distilkit.cards.objectives import structural as _structural  # noqa: F401
