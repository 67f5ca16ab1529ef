"""`--set` values that run a shipped recipe in miniature for the slow suite: every stage that trains trains
``steps`` steps (evaluated once, at the end), on fewer scenes; the stages that only evaluate (``steps: 0``) stay so,
and the models, grids, images and sampler step counts stay the recipe's."""

from __future__ import annotations

from pathlib import Path

import yaml


def shrink(recipe: Path, steps: int, **data: object) -> list[str]:
    """``--set`` values: ``steps`` (and ``eval_every``) for each stage of ``recipe`` that trains, and ``data``'s
    parameters (e.g. ``num_train=2``)."""
    stages = yaml.safe_load(recipe.read_text())["stages"]
    sets = [f"data.params.{k}={v}" for k, v in data.items()]
    for name, spec in stages.items():
        if spec.get("train", {}).get("steps", 1) != 0:
            sets += [f"stages.{name}.train.steps={steps}", f"stages.{name}.train.eval_every={steps}"]
    return sets
