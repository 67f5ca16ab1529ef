"""The device a stage trains on: ``train.device`` (``auto``: CUDA where there is a GPU, else the CPU)."""

from __future__ import annotations

from typing import Any, Iterable

import torch


def pick_device(name: str) -> torch.device:
    """``train.device`` as a torch device (``auto``: CUDA where a GPU is available, else the CPU)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def stage_devices(recipe: Any, only: Iterable[str] | None = None) -> dict[str, torch.device]:
    """The device each stage of a validated recipe (:class:`~distilkit.recipe.schema.Recipe`) trains on, by stage
    name, in the recipe's order; ``only``: just these stages and the stages they need (``--stage``; names the recipe
    does not have are left to the run to refuse)."""
    names = list(recipe.stages)
    if only:
        from distilkit.recipe.graph import needed_stages

        known = {n for n in only if n in recipe.stages}
        if known:
            keep = needed_stages(recipe, known)
            names = [n for n in names if n in keep]
    return {n: pick_device(recipe.stages[n].train.device) for n in names}


__all__ = ["pick_device", "stage_devices"]
