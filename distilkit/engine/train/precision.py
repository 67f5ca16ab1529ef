"""The forward's precision (``train.precision``): one context for the trainer, the teacher store's build and the
step benchmark, so that the teacher the store runs computes in the type the live teacher does."""

from __future__ import annotations

import contextlib
from typing import Any

import torch

AUTOCAST = {"bf16": torch.bfloat16, "fp16": torch.float16}


def autocast(device: torch.device, precision: str) -> Any:
    """The forward's context for ``precision``: nothing for fp32, else autocast to bf16 or fp16 on ``device``."""
    if precision == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=AUTOCAST[precision])


__all__ = ["AUTOCAST", "autocast"]
