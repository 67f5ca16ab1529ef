"""The device a stage trains on: ``train.device`` (``auto``: CUDA where there is a GPU, else the CPU)."""

from __future__ import annotations

import torch


def pick_device(name: str) -> torch.device:
    """``train.device`` as a torch device (``auto``: CUDA where a GPU is available, else the CPU)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


__all__ = ["pick_device"]
