"""Reading a recipe: YAML parsed with ``yaml.safe_load`` only, ``--set PATH=VALUE`` overrides applied by dotted path
(``*`` matching every stage) before validation, and the structure validated against the schema
(:mod:`distilkit.recipe.schema`) with every problem named by its path."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from distilkit.errors import RecipeError
from distilkit.recipe.problems import pydantic_problems
from distilkit.recipe.schema import Recipe


def parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise RecipeError([("", f"{where}malformed YAML: {problem}")], source) from None


def recipe_from_dict(data: Any, source: str = "recipe") -> Recipe:
    if not isinstance(data, dict):
        raise RecipeError([("", f"a recipe must be a YAML mapping, got {type(data).__name__}")], source)
    try:
        return Recipe.model_validate(data)
    except ValidationError as err:
        raise RecipeError(pydantic_problems(err, model=Recipe), source) from None


def set_path(data: dict[str, Any], path: str, value: Any, source: str, where: str) -> int:
    """Set ``data[a][b][0]...`` from the dotted path ``a.b.0...`` (mappings are created on the way); a ``*`` part
    stands for every key of the mapping (every item of the list) found there, as in ``stages.*.train.steps``.
    Returns the number of places set; a path whose wildcard matches nothing is an error that names it."""
    parts = path.split(".")
    if "*" in parts:
        places = _expand(data, parts)
        if not places:
            i = parts.index("*")
            raise RecipeError([(where, f"{path}: matches nothing (no field of the recipe is at that path; the first "
                                       f"'*' stands for the entries of {'.'.join(parts[:i]) or 'the recipe'})")],
                              source)
        for place in places:
            set_path(data, ".".join(place), value, source, where)
        return len(places)
    node = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise RecipeError([(where, f"{path}: {'.'.join(parts[:i]) or 'the recipe'} is a list of {len(node)}; "
                                           f"{part!r} is not an index of it")], source)
            key: Any = int(part)
        elif isinstance(node, dict):
            key = part
        else:
            raise RecipeError([(where, f"{path}: {'.'.join(parts[:i])} is a {type(node).__name__}, not a mapping or "
                                       "a list")], source)
        if last:
            node[key] = copy.deepcopy(value)
            return 1
        else:
            if isinstance(node, dict) and node.get(key) is None:
                if parts[:i] == ["stages"]:  # a new stage from a typo would fail later with a vaguer message
                    import difflib

                    close = difflib.get_close_matches(key, [str(k) for k in node], n=1)
                    hint = f"; did you mean {close[0]!r}?" if close else ""
                    raise RecipeError([(where, f"{path}: the recipe has no stage {key!r}{hint} (stages: "
                                               f"{', '.join(map(str, node)) or 'none'})")], source)
                node[key] = {}
            node = node[key]
    return 0  # not reached: the last part returns


def _expand(node: Any, parts: list[str]) -> list[list[str]]:
    """The concrete paths a dotted path with ``*`` parts names in ``node``: each ``*`` stands for every key of the
    mapping (item of the list) there; a branch that does not reach the path's last part names nothing."""
    if not parts:
        return [[]]
    head, rest = parts[0], parts[1:]
    if head == "*":
        keys = list(node) if isinstance(node, dict) else list(range(len(node))) if isinstance(node, list) else []
    else:
        keys = [head]
    out = []
    for key in keys:
        if not rest:
            out.append([str(key)])
            continue
        child = (node.get(key) if isinstance(node, dict) else
                 node[int(key)] if isinstance(node, list) and str(key).isdigit() and int(key) < len(node) else None)
        if child is None and "*" not in rest:  # created on the way, as a path without wildcards would be
            out.append([str(key), *rest])
        elif isinstance(child, (dict, list)):
            out += [[str(key), *tail] for tail in _expand(child, rest)]
    return out


def parse_overrides(items: list[str], source: str = "--set") -> dict[str, Any]:
    """``PATH=VALUE`` items of the command line (``stages.student.optimizer.lr=0.01``) as path -> value, each value
    read as YAML (``0.01`` a number, ``[1, 2]`` a list, ``true`` a boolean, anything else a string)."""
    out: dict[str, Any] = {}
    for item in items:
        path, eq, text = item.partition("=")
        if not eq or not path.strip() or any(not part for part in path.strip().split(".")):
            raise RecipeError([("--set", f"{item!r}: expected PATH=VALUE with a dotted path, e.g. "
                                         "stages.student.optimizer.lr=0.01")], source)
        out[path.strip()] = parse_yaml(text, f"--set {path.strip()}")
    return out


def load_recipe(path: str | Path, overrides: dict[str, Any] | None = None) -> Recipe:
    """Read and validate the structure of a recipe file (``yaml.safe_load``; nothing is executed), with
    ``overrides`` (dotted path -> value, :func:`parse_overrides`) applied first and validated like the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecipeError([("", f"cannot read recipe: {exc}")], str(path)) from None
    data = parse_yaml(text, str(path))
    if overrides:
        if not isinstance(data, dict):
            raise RecipeError([("", f"a recipe must be a YAML mapping, got {type(data).__name__}")], str(path))
        for key, value in overrides.items():
            set_path(data, key, value, str(path), f"--set {key}")
    return recipe_from_dict(data, str(path))
