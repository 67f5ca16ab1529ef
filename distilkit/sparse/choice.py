"""The sparse backend a user asked for (``DISTILKIT_SPARSE``, or :func:`distilkit.sparse.backend.using`), read
without importing torch, so that ``distilkit validate --static`` and ``sweep --plan`` check the variable before a
run; which backend computes a call is :mod:`distilkit.sparse.backend`'s."""

from __future__ import annotations

import os

from distilkit.errors import DistilkitError

ENV = "DISTILKIT_SPARSE"
CHOICES = ("auto", "torch", "spconv", "spconv-triton")

_override: list[str] = []  # :func:`distilkit.sparse.backend.using`'s choices, innermost last


class SparseBackendError(DistilkitError):
    """A requested sparse backend cannot run here (not installed, not for this device, no backward), or cannot take
    a call (its dtype, autocast's dtype, gradients)."""


def requested() -> str:
    """The backend asked for: the innermost :func:`~distilkit.sparse.backend.using`, else ``DISTILKIT_SPARSE``, else
    ``auto``."""
    if _override:
        return _override[-1]
    value = os.environ.get(ENV, "auto").strip().lower() or "auto"
    if value not in CHOICES:
        raise SparseBackendError(f"{ENV}={value!r}: choose one of {', '.join(CHOICES)}")
    return value


__all__ = ["CHOICES", "ENV", "SparseBackendError", "requested"]
