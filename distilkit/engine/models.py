"""Building a stage's models: the adapter from its resolved spec (with recorded taps), the frozen teacher."""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from distilkit.adapter import Adapter
from distilkit.data.info import DataInfo
from distilkit.engine.io import load_weights
from distilkit.engine.recorders import attach_recorders
from distilkit.engine.resolve import ResolvedModel


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def build_model(model: ResolvedModel, info: DataInfo, role: str = "student") -> Adapter:
    """The adapter, with the recipe's recorded taps attached (``model.taps`` in a recipe)."""
    built = model.cls(model.params, info)
    attach_recorders(built, model.hooks, role)
    return built


def freeze(model: nn.Module) -> nn.Module:
    """Teacher semantics: eval mode (BatchNorm statistics frozen) and no gradients."""
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def load_teacher(model: ResolvedModel, info: DataInfo, checkpoint: Path, device: torch.device) -> Adapter:
    """The frozen teacher: the adapter built from its params, its weights read by the adapter (all must fit)."""
    teacher = build_model(model, info, "teacher")
    load_weights(teacher, model.cls.read_weights(str(checkpoint)), True, f"teacher {checkpoint}")
    return freeze(teacher.to(device))  # type: ignore[return-value]
