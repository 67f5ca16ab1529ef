"""A written recipe checked as ``distilkit validate --no-memory`` checks it: resolved (names, taps, alignments,
edges), what its run would meet (the data, weights files, sparse convolutions), then each distilling stage's terms
on a dry batch (the first step, as the run's)."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def confirm(path: str | Path, run_terms: bool = True) -> list[tuple[str, str]]:
    """The (field, problem) lines ``validate`` would print for the recipe at ``path`` (none: it validates)."""
    from distilkit.engine.assemble.checks import run_problems
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.engine.memory.probe import StepFailure, check_terms
    from distilkit.errors import RecipeError
    from distilkit.recipe import load_recipe

    try:
        res = resolve(load_recipe(path), str(path))
    except RecipeError as exc:
        return list(exc.problems)
    problems = run_problems(res)[1]
    if problems or not run_terms:
        return problems
    for name in res.order:
        if res.stages[name].distill:
            try:
                check_terms(res, name)
            except StepFailure as exc:
                problems.append((exc.field, exc.problem))
    return problems


def resolved(data: dict[str, Any]) -> Any:
    """A recipe dict resolved (raises :class:`~distilkit.errors.RecipeError` listing its problems)."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    return resolve(recipe_from_dict(data, "distilkit init"), "distilkit init")


__all__ = ["confirm", "resolved"]
