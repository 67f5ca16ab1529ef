"""What ``distilkit init`` is given, checked: the adapters, their parameters, the data that serves both (the first
registered dataset that does, by default), the auxiliary stages an input only a model gives needs, and a trained
teacher read from its run."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError


class InitError(DistilkitError):
    """What keeps ``distilkit init`` from writing a recipe, in lines."""


def from_checkpoint(source: str) -> tuple[str, dict[str, Any], dict[str, Any], str]:
    """(adapter, its parameters, the run's data — ``{}`` without a resolved recipe beside it —, the checkpoint
    file) of a run folder or a distilkit checkpoint (read with ``weights_only=True``; the weights are not used)."""
    from distilkit.engine.assemble.runs import checkpoint_path, run_config
    from distilkit.weights import load_checkpoint

    path = checkpoint_path(source, "any")
    ckpt = load_checkpoint(path)
    adapter = ckpt.get("adapter")
    if not isinstance(adapter, str):
        raise InitError(f"{path}: the checkpoint names no adapter")
    return (adapter, dict(ckpt.get("adapter_params") or {}), dict(run_config(path).get("data") or {}),
            str(Path(path).resolve()))  # absolute: the recipe is read from wherever it is written


def lookup(registry: Any, name: str) -> None:
    if name not in registry.names():
        raise InitError(registry.unknown_message(name))


def data_params_for(dataset: str, given: dict[str, Any], cards: list[Any]) -> dict[str, Any]:
    """The data parameters: the adapters' needs (``DATA_PARAMS``, e.g. a camera) under the user's."""
    out: dict[str, Any] = {}
    for card in cards:
        out.update(card.DATA_PARAMS)
    return {**out, **given}


def serves(dataset: str, params: dict[str, Any], models: dict[str, tuple[str, dict[str, Any]]]
           ) -> tuple[str | None, Any]:
    """(why the data cannot serve both models, or None where it can; the data's info, or None where its parameters
    are wrong), by the models' inputs (an aux input counts as served)."""
    from distilkit.registry import ADAPTERS, DATASETS

    entry = DATASETS.entry(dataset)
    try:
        info = entry.meta["info"](entry.meta["params"](**params))
    except Exception as exc:  # a folder dataset without its root, a bad parameter
        errors = getattr(exc, "errors", None)
        if callable(errors):
            need = sorted({".".join(map(str, e["loc"])) for e in errors() if e.get("type") == "missing"})
            if need:
                return f"{dataset} needs {', '.join(need)} (--data-params)", None
        return f"{dataset}: {_problems(exc)}", None
    lacks = []
    for role, (adapter, p) in models.items():
        card = ADAPTERS.card(adapter)
        need = card.inputs(card.Params(**p)) - info.fields - set(card.AUX_INPUTS)
        if need:
            lacks.append(f"the {role} {adapter!r} reads {', '.join(sorted(need))}")
    return (f"{dataset} lacks what {'; '.join(lacks)}" if lacks else None), info


def dataset_reasons(models: dict[str, tuple[str, dict[str, Any]]], given: dict[str, Any]) -> dict[str, str | None]:
    """Every registered dataset, in the registry's order, and why it cannot serve both models with its default
    parameters (and the adapters' ``DATA_PARAMS``, under ``given``); None where it can."""
    from distilkit.registry import ADAPTERS, DATASETS

    cards = [ADAPTERS.card(a) for a, _ in models.values()]
    return {name: serves(name, data_params_for(name, given, cards), models)[0] for name in DATASETS.names()}


def pick_dataset(models: dict[str, tuple[str, dict[str, Any]]], given: dict[str, Any]) -> str:
    """The first registered dataset that serves both models (:func:`dataset_reasons`); an error listing why each
    does not."""
    reasons = dataset_reasons(models, given)
    for name, why in reasons.items():
        if why is None:
            return name
    raise InitError("no registered dataset serves both models: " + "; ".join(w for w in reasons.values() if w))


def aux_stages(models: dict[str, tuple[str, dict[str, Any]]], info: Any) -> tuple[dict, dict]:
    """The auxiliary stages the models' inputs need (an input the data lacks that ``AUX_INPUTS`` names: a stage of
    that adapter named after the input) and each role's edges."""
    from distilkit.registry import ADAPTERS

    stages: dict[str, tuple[str, dict[str, Any]]] = {}
    edges: dict[str, dict[str, str]] = {}
    for role, (adapter, params) in models.items():
        card = ADAPTERS.card(adapter)
        for name in sorted(card.inputs(card.Params(**params)) - info.fields):
            if name in card.AUX_INPUTS:
                stages[name] = (card.AUX_INPUTS[name], {})
                edges.setdefault(role, {})[name] = name
    return stages, edges


def _problems(exc: Exception) -> str:
    """A parameters error in one line: each field and what is wrong with it (pydantic's), else the message."""
    errors = getattr(exc, "errors", None)
    if callable(errors):
        return "; ".join(f"{'.'.join(map(str, e['loc'])) or '(parameters)'}: {e['msg']}" for e in errors())
    return str(exc).splitlines()[0]


def check_models(models: dict[str, tuple[str, dict[str, Any]]]) -> None:
    """Each model's parameters valid for its adapter (an :class:`InitError` naming each field otherwise)."""
    from distilkit.registry import ADAPTERS

    problems = []
    for role, (adapter, params) in models.items():
        try:
            ADAPTERS.card(adapter).Params.model_validate(params)
        except Exception as exc:
            problems.append(f"--{role}-params for {adapter!r}: {_problems(exc)}")
    if problems:
        raise InitError("; ".join(problems))


__all__ = ["InitError", "aux_stages", "check_models", "data_params_for", "dataset_reasons", "from_checkpoint", "lookup",
           "pick_dataset", "serves"]
