"""A recipe's validation errors as lines a user reads: each with the dotted path of the field (``stages.student.
train.steps``), and for an unknown key the keys that would have been valid there, the nearest first."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError


def format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _model_at(model: Any, loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model class a location inside ``model`` (a class) falls in: field by field, through the values
    of dicts (a part of ``loc`` is then their key) and the items of lists (an index), None where it leaves them."""
    import typing

    def unwrap(annotation: Any) -> tuple[Any, bool]:
        """(the model or container an annotation holds, whether the next part of the location is a key/index)."""
        origin = typing.get_origin(annotation)
        if origin in (dict, list):
            return typing.get_args(annotation)[-1], True
        inner = [a for a in typing.get_args(annotation) if a is not type(None)]
        if origin is not None and len(inner) == 1:  # Optional[X]
            return unwrap(inner[0])
        return annotation, False

    node: Any = model
    keyed = False
    for part in loc:
        if keyed:  # a dict's key or a list's index: its value's annotation
            node, keyed = unwrap(node)
            continue
        if not (isinstance(node, type) and issubclass(node, BaseModel)):
            return None
        field = node.model_fields.get(part) or next((f for f in node.model_fields.values() if f.alias == part), None)
        if field is None:
            return None
        node, keyed = unwrap(field.annotation)
    if keyed:
        return None
    return node if isinstance(node, type) and issubclass(node, BaseModel) else None


def model_keys(model: type[BaseModel]) -> list[str]:
    """The keys a model accepts, as a recipe writes them (aliases where a field has one)."""
    return sorted(f.alias or name for name, f in model.model_fields.items())


def unknown_key_message(key: Any, valid: list[str]) -> str:
    """``unknown key 'x'`` with the nearest valid key and the valid ones."""
    import difflib

    close = difflib.get_close_matches(str(key), valid, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key {str(key)!r}{hint} (valid: {', '.join(valid)})"


def pydantic_problems(err: ValidationError, prefix: str = "", model: type[BaseModel] | None = None) -> \
        list[tuple[str, str]]:
    """(path, message) per validation error; an unknown key names the valid keys of ``model`` (the class validated)
    at its place, and the nearest one."""
    problems = []
    for e in err.errors():
        loc = tuple(p for p in e["loc"] if p not in ("function-after",) and not str(p).startswith("function-"))
        path = format_loc(loc)
        if prefix:
            path = f"{prefix}.{path}" if path and not path.startswith("[") else prefix + path
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            at = _model_at(model, loc[:-1]) if model is not None and loc else None
            msg = unknown_key_message(loc[-1], model_keys(at)) if at is not None and loc else "unknown key"
        elif msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        problems.append((path, msg))
    return problems
