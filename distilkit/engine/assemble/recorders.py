"""Taps without adapter code: record a submodule's output, its input, or the value one of its methods returns, by
its dotted path — MMRazor's recorder kinds, from the ``RECORDERS`` registry (plugins add their own; the
built-in ones below are declared in :mod:`distilkit.cards.recorders`).

A recipe declares ``model: {..., taps: {mid: {module: net.completion.blocks.1, kind: volume_features}}}`` (``at:
output`` by default; ``at: input``; ``at: method, method: encode``); the recorded value joins the adapter's output
dict as the tap ``mid`` on every forward pass and is checked against its declared kind on the first batch like
every other tap. A registered recorder is ``install(submodule, spec, record) -> None``: it arranges for
``record(value)`` to be called whenever the submodule produces the value it records.
"""

from __future__ import annotations

import difflib
import functools
from typing import Any, Callable

from torch import nn

from distilkit.errors import TapError
from distilkit.registry import RECORDERS

Record = Callable[[Any], None]


def _output(sub: nn.Module, spec: Any, record: Record) -> None:
    sub.register_forward_hook(lambda _m, _args, output: record(output))


def _input(sub: nn.Module, spec: Any, record: Record) -> None:
    sub.register_forward_hook(lambda _m, args, _output: record(args[0] if args else None))


def _method(sub: nn.Module, spec: Any, record: Record) -> None:
    name = getattr(spec, "method", None)
    original = getattr(sub, name, None) if name else None
    if not callable(original):
        raise TapError(f"recorder 'method' needs `method:` naming a method of {type(sub).__name__} (got {name!r})")

    @functools.wraps(original)
    def wrapped(*args: Any, **kwargs: Any) -> Any:
        value = original(*args, **kwargs)
        record(value)
        return value

    setattr(sub, name, wrapped)  # an instance attribute: this model only


def attach_recorders(model: nn.Module, hooks: dict[str, Any], role: str = "model") -> None:
    """Record each ``hooks[name]`` (a spec with ``module``, ``kind``, ``at`` and ``method``, or ``of`` another tap)
    into the model's outputs; a spec with ``collapse`` gives the value collapsed over height (at the end of the
    model's forward, with the batch's size: sparse voxels of a sample without any still make its row)."""
    if not hooks:
        return
    modules = dict(model.named_modules())
    recorded: dict[str, Any] = {}
    derived = {name: spec for name, spec in hooks.items() if getattr(spec, "of", None) is not None}
    collapsed = [name for name, spec in hooks.items() if getattr(spec, "collapse", None) is not None]
    for name, spec in hooks.items():
        if name in derived:
            continue
        sub = modules.get(spec.module)
        if sub is None or spec.module == "":
            close = difflib.get_close_matches(spec.module, [m for m in modules if m], n=3, cutoff=0.5)
            hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else ""
            raise TapError(f"{role} tap {name!r}: {type(model).__name__} has no submodule {spec.module!r}{hint}")
        RECORDERS.get(spec.at)(sub, spec, lambda value, name=name: recorded.__setitem__(name, value))

    def merge(_mod: nn.Module, args: tuple[Any, ...], outputs: dict[str, Any]) -> dict[str, Any]:
        out = {**outputs, **recorded}
        recorded.clear()
        if collapsed:
            size = _batch_size(args)
            for name in collapsed:  # each of a voxel tap (validate): never of another collapsed one
                spec = hooks[name]
                source = spec.of if name in derived else name
                if source in out:
                    out[name] = _collapse(out[source], spec.collapse, size, f"{role} tap {name!r}")
                elif name in derived:
                    raise TapError(f"{role} tap {name!r} is made of tap {spec.of!r}, which the model did not return "
                                   f"(it returned: {', '.join(out)})")
        return out

    model.register_forward_hook(merge)
    model.tap_kinds = {**getattr(model, "tap_kinds", {}), **{n: s.kind for n, s in hooks.items()}}



def _batch_size(args: tuple[Any, ...]) -> int | None:
    """The batch size of a forward's first argument (a :class:`~distilkit.data.batch.Batch`), if it says one."""
    try:
        size = getattr(args[0], "size", None) if args else None
    except (KeyError, TypeError):
        return None
    return size if isinstance(size, int) else None


def _collapse(value: Any, how: str, batch: int | None, what: str) -> Any:
    from distilkit.losses.bev import collapse_height

    try:
        return collapse_height(value, how, batch=batch)
    except ValueError as exc:
        raise TapError(f"{what} collapses its value over height: {exc}") from None
