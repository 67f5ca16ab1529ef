"""The stages of a recipe as a graph: each stage's edges (teacher, initial weights, labels, auxiliary models) name
the stages it reads; the order they run in, and the stages a subset needs."""

from __future__ import annotations

from distilkit.errors import RecipeError
from distilkit.recipe.schema import Recipe


def needed_stages(recipe: Recipe, names: set[str]) -> set[str]:
    """``names`` and every stage they read (:meth:`StageSpec.edges`), transitively (references checked by
    :func:`stage_order`)."""
    out: set[str] = set()
    todo = list(names)
    while todo:
        name = todo.pop()
        if name in out:
            continue
        out.add(name)
        todo += list(recipe.stages[name].edges().values())
    return out


def stage_order(recipe: Recipe) -> list[str]:
    """Stage names in dependency order (a teacher stage before its students)."""
    order: list[str] = []
    state: dict[str, int] = {}
    problems: list[tuple[str, str]] = []

    def visit(name: str, path: list[str]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            problems.append((f"stages.{name}", f"cycle of teacher/init stages: {' -> '.join(path + [name])}"))
            return
        state[name] = 1
        for field_name, upstream in recipe.stages[name].edges().items():
            if upstream not in recipe.stages:
                import difflib

                close = difflib.get_close_matches(upstream, list(recipe.stages), n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                problems.append((f"stages.{name}.{field_name}.from", f"no stage named {upstream!r}{hint}"))
            else:
                visit(upstream, path + [name])
        state[name] = 2
        order.append(name)

    for name in recipe.stages:
        visit(name, [])
    if problems:
        raise RecipeError(problems)
    return order
