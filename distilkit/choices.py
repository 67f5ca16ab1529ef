"""Choices a component makes where the papers and their authors' released code differ, or where neither pins a
detail: each registered component may list them as ``CHOICES``, and ``distilkit list objectives --markdown``
(docs/reference/objectives.md) gathers them from every registry into one table, so the documentation cannot drift
from the code that makes the choice."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterator


@dataclass(frozen=True)
class Choice:
    """One choice: what it is about, what distilkit does by default, what the paper and the released code say, and
    how to get the other behaviour (empty where there is no switch)."""

    topic: str
    default: str
    paper: str
    code: str
    option: str = ""


def component_choices() -> Iterator[tuple[str, str, Choice]]:
    """(kind, registered name, choice) for every choice of every registered component, registry by registry."""
    from distilkit.registry import ADAPTERS, DATASETS, OBJECTIVES, TASK_LOSSES

    for kind, registry in (("adapter", ADAPTERS), ("objective", OBJECTIVES), ("task loss", TASK_LOSSES),
                           ("dataset", DATASETS)):
        for entry in registry:
            obj: Any = entry.obj
            for choice in getattr(obj, "CHOICES", ()):
                yield kind, entry.name, choice


__all__ = ["Choice", "component_choices"]
