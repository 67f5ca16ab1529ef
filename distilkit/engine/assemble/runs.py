"""Models from runs: one way to rebuild a model from a stage's run folder (or a checkpoint file), for teachers,
initial weights, scoring the best checkpoint, ``distilkit complete`` and predictions.

A run folder holds ``checkpoints/{best,last}.pt`` (the student's weights, the adapter's name and parameters) and
``recipe.resolved.yaml`` (the data it was trained on). A caller that knows the model (a recipe's resolved teacher,
with the taps the stage records) passes it; otherwise it is read from the checkpoint and the folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from distilkit.adapter import Adapter
from distilkit.engine.store.checkpoints import checkpoint_file
from distilkit.weights import load_checkpoint, load_weights, whole_problem
from distilkit.errors import DataError


def checkpoint_path(source: str | Path, which: str = "best") -> Path:
    """The checkpoint file of ``source``: a file as it is, or a run folder's ``checkpoints/<which>.pt``
    (``which="any"``: best, else last); what a folder holds named otherwise (``store.checkpoints``)."""
    return checkpoint_file(source, which)


def run_config(checkpoint: Path) -> dict[str, Any]:
    """The stage's resolved recipe beside a run's checkpoint (``{}`` when there is none)."""
    import yaml

    resolved = checkpoint.parent.parent / "recipe.resolved.yaml"
    if not resolved.is_file():
        return {}
    try:
        return yaml.safe_load(resolved.read_text(encoding="utf-8")) or {}
    except yaml.YAMLError as exc:
        raise DataError(f"{resolved}: not readable YAML ({exc})") from None


def _model_of(checkpoint: Path, config: dict[str, Any]) -> tuple[Any, Any]:
    """(resolved model, data info) from a checkpoint's adapter name and parameters and its run's data."""
    from distilkit.engine.assemble.resolved import ResolvedModel
    from distilkit.registry import ADAPTERS, DATASETS, load_plugins

    load_plugins()
    ckpt = load_checkpoint(checkpoint)
    name = ckpt.get("adapter")
    if name not in ADAPTERS:
        raise DataError(f"{checkpoint}: the checkpoint names adapter {name!r}, which is not installed "
                        f"(installed: {', '.join(ADAPTERS.names())})")
    cls = ADAPTERS.get(name)
    params = cls.Params.model_validate(ckpt.get("adapter_params") or {})
    data = config.get("data") or {"dataset": "synthetic-scenes", "params": {}}
    entry = DATASETS.entry(data["dataset"])
    info = entry.meta["info"](entry.meta["params"].model_validate(data.get("params") or {}))
    return ResolvedModel(name, cls, params), info


def build_model(model: Any, info: Any, role: str = "student") -> Adapter:
    """The adapter of a resolved model, with the recipe's recorded taps attached (``model.taps`` in a recipe)."""
    from distilkit.engine.assemble.recorders import attach_recorders

    built = model.cls(model.params, info)
    attach_recorders(built, model.hooks, role)
    return built


def freeze(model: torch.nn.Module) -> torch.nn.Module:
    """A frozen model's semantics: eval mode (BatchNorm statistics kept) and no gradients."""
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    return model


def load_run(source: str | Path, which: str = "best", *, model: Any = None, info: Any = None,
             device: torch.device | str = "cpu", role: str = "model", frozen: bool = True,
             strict: bool = True) -> Adapter:
    """The model of a run folder's ``which`` checkpoint (or of a checkpoint file), its weights read by the
    adapter's ``read_weights``. ``model``/``info``: the resolved model and data to build it for (default: what the
    checkpoint and its folder record). ``frozen``: eval mode, no gradients (teachers, auxiliary models).

    Building draws no random numbers from the caller's stream (the random initial weights are replaced)."""
    path = checkpoint_path(source, which)
    if model is None or info is None:
        found, found_info = _model_of(path, run_config(path))
        model, info = model or found, info or found_info
    with torch.random.fork_rng(devices=[]):
        built = build_model(model, info, role)
    weights = model.cls.read_weights(str(path))
    if whole_problem(weights):
        raise DataError(f"{role} {path}: {whole_problem(weights)}")
    load_weights(built, weights, strict, f"{role} {path}")
    built = built.to(device)
    return freeze(built) if frozen else built.train(False)  # type: ignore[return-value]


def checkpoint_step(source: str | Path, which: str = "best") -> int:
    """The step a run's checkpoint was written at."""
    return int(load_checkpoint(checkpoint_path(source, which)).get("step", 0))


__all__ = ["build_model", "checkpoint_path", "checkpoint_step", "freeze", "load_run", "run_config"]
