"""A stage that runs out of memory: whether an exception is an allocation failure, and the one-line error that says
where, at what size and what to lower (``distilkit validate`` estimates the need beforehand:
:mod:`distilkit.engine.memory.estimate`)."""

from __future__ import annotations

from typing import Any

from distilkit.errors import DistilkitError


class OutOfMemoryError(DistilkitError):
    """A stage needed more memory than the machine (or the GPU) has."""


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether an exception is an allocation failure (CPU allocator, CUDA, or Python's MemoryError)."""
    if isinstance(exc, MemoryError):
        return True
    import torch

    if isinstance(exc, torch.OutOfMemoryError):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower()
                                              or "Cannot allocate memory" in text)


def _cause(exc: BaseException) -> str:
    """The failed allocation in a few words (the allocator's message is long)."""
    import re

    text = str(exc)
    cpu = re.search(r"tried to allocate (\d+) bytes", text)
    if cpu:
        return f"an allocation of {int(cpu.group(1)) / 2**20:,.0f} MiB failed"
    gpu = re.search(r"Tried to allocate ([\d.]+ [KMG]iB)", text)
    if gpu:
        return f"an allocation of {gpu.group(1)} on the GPU failed"
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first if len(first) <= 120 else first[:117].rsplit(" ", 1)[0] + "..."


def out_of_memory(stage: Any, info: Any, exc: BaseException, kept: str) -> OutOfMemoryError:
    """The one-line error for a stage that ran out of memory: where, at what size, and what to lower."""
    grid = f"a {'x'.join(map(str, info.grid.shape))} grid" if getattr(info, "grid", None) is not None else "its data"
    return OutOfMemoryError(
        f"stage {stage.name!r} ran out of memory ({_cause(exc)}; train.batch_size {stage.spec.train.batch_size}, "
        f"{grid}, adapter {stage.student.adapter}); {kept}. Lower train.batch_size, the grid (data.params.scale) or "
        "the model's size; `distilkit validate` estimates the memory a training step needs.")


__all__ = ["OutOfMemoryError", "is_out_of_memory", "out_of_memory"]
