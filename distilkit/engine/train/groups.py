"""Which parameters of a stage train, and in which optimizer group: the recipe's ``freeze`` globs and
``optimizer.param_groups`` over the qualified names ``student.*``, ``task.<term>.*``, ``distill.<objective>.*``,
``connector.<objective>.*`` (a pattern without a dot also matches the last part of a name)."""

from __future__ import annotations

from fnmatch import fnmatchcase
from typing import Any

from torch import nn

from distilkit.errors import DistilkitError


def matches(pattern: str, name: str) -> bool:
    """Whether ``name`` fits the glob ``pattern`` (a pattern without a dot: also the name's last part)."""
    return fnmatchcase(name, pattern) or ("." not in pattern and fnmatchcase(name.rsplit(".", 1)[-1], pattern))


def freeze(stage: Any, named: list[tuple[str, nn.Parameter]]) -> None:
    """Keep the parameters that ``freeze`` names, or that a parameter group gives ``lr_scale: 0``, as they are (no
    gradient, no optimizer state). A ``freeze`` glob that matches nothing is an error (a typo would otherwise train
    what it meant to keep)."""
    for pat in stage.spec.freeze:
        hit = [p for n, p in named if matches(pat, n)]
        if not hit:
            raise DistilkitError(f"stage {stage.name!r}: freeze {pat!r} matches no parameter (names look "
                                 f"like {', '.join(n for n, _ in named[:3])})")
        for p in hit:
            p.requires_grad_(False)
    for group in stage.param_groups:
        if group["lr_scale"] == 0:
            for n, p in named:
                first = next((g for g in stage.param_groups if matches(g["match"], n)), None)
                if first is group:  # first match wins, as for the optimizer's groups
                    p.requires_grad_(False)


def param_groups(stage: Any, trainables: list[tuple[str, nn.Parameter]]) -> list[dict[str, Any]]:
    """Optimizer groups: each trainable parameter joins the first group whose ``match`` fits its name, the rest the
    default group."""
    o = stage.spec.optimizer
    groups = [{"params": [], "lr": o.lr * g["lr_scale"], "name": g["match"],
               **({"weight_decay": g["weight_decay"]} if g.get("weight_decay") is not None else {})}
              for g in stage.param_groups]
    rest: dict[str, Any] = {"params": [], "lr": o.lr, "name": "default"}
    for name, p in trainables:
        for spec, group in zip(stage.param_groups, groups):
            if matches(spec["match"], name):
                group["params"].append(p)
                break
        else:
            rest["params"].append(p)
    return [g for g in (rest, *groups) if g["params"]]


__all__ = ["freeze", "matches", "param_groups"]
