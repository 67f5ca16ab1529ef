"""Which form the torch path of a sparse convolution computes in: ``table`` (``distilkit.sparse.table``: a
neighbour table, one gather and one GEMM per chunk of rows) or ``loop`` (``distilkit.sparse.function``: a gather,
a GEMM and a scatter-add per kernel offset), chosen by ``DISTILKIT_SPARSE_FORM`` (``auto``: the table on CUDA, where
launches dominate, the loop on the CPU, where it is 3-4x faster: docs/how-to/gpus.md) or
:func:`using_form`."""

from __future__ import annotations

import contextlib
import os
from typing import Iterator

FORM_ENV = "DISTILKIT_SPARSE_FORM"
FORMS = ("auto", "table", "loop")
AUTO_FORM = {"cuda": "table"}  # device type -> the torch path's form under ``auto``; others: ``CPU_FORM``
CPU_FORM = "loop"  # the faster form on the CPU (``distilkit bench sparse`` measures both: docs/how-to/gpus.md)
_forms: list[str] = []  # :func:`using_form`'s choices, innermost last


def form(device_type: str) -> str:
    """The torch path's form on ``device_type``: the innermost :func:`using_form`, else ``DISTILKIT_SPARSE_FORM``,
    else ``auto`` — the neighbour table (``distilkit.sparse.table``) on CUDA, ``CPU_FORM`` elsewhere."""
    want = _forms[-1] if _forms else (os.environ.get(FORM_ENV, "auto").strip().lower() or "auto")
    if want not in FORMS:
        raise ValueError(f"{FORM_ENV}={want!r}: choose one of {', '.join(FORMS)}")
    return AUTO_FORM.get(device_type, CPU_FORM) if want == "auto" else want


@contextlib.contextmanager
def using_form(name: str) -> Iterator[None]:
    """Run the torch path's convolutions inside the block in form ``name`` (``table`` or ``loop``; ``auto``)."""
    if name not in FORMS:
        raise ValueError(f"sparse form {name!r}: choose one of {', '.join(FORMS)}")
    _forms.append(name)
    try:
        yield
    finally:
        _forms.pop()


__all__ = ["AUTO_FORM", "CPU_FORM", "FORMS", "FORM_ENV", "form", "using_form"]
