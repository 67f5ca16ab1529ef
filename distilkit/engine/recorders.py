"""Taps without adapter code: record any submodule's output (or input) by its dotted path.

A recipe declares ``model: {..., taps: {mid: {module: net.completion.blocks.1, kind: volume_features}}}``;
a forward hook on that submodule records its value on every forward pass, and the adapter's output
dict gains the tap ``mid`` (as OpenMMLab MMRazor's recorders do). The recorded tap is checked against its
declared kind on the first batch like every other tap.
"""

from __future__ import annotations

import difflib
from typing import Any

from torch import nn

from distilkit.errors import TapError


def attach_recorders(model: nn.Module, hooks: dict[str, Any], role: str = "model") -> None:
    """Record each ``hooks[name]`` (a spec with ``module``, ``kind``, ``at``) into the model's outputs."""
    if not hooks:
        return
    modules = dict(model.named_modules())
    recorded: dict[str, Any] = {}
    for name, spec in hooks.items():
        sub = modules.get(spec.module)
        if sub is None or spec.module == "":
            close = difflib.get_close_matches(spec.module, [m for m in modules if m], n=3, cutoff=0.5)
            hint = f"; did you mean {' or '.join(map(repr, close))}?" if close else ""
            raise TapError(f"{role} tap {name!r}: {type(model).__name__} has no submodule {spec.module!r}{hint}")

        def record(_mod: nn.Module, args: tuple[Any, ...], output: Any, name: str = name, at: str = spec.at) -> None:
            recorded[name] = (args[0] if args else None) if at == "input" else output

        sub.register_forward_hook(record)

    def merge(_mod: nn.Module, _args: tuple[Any, ...], outputs: dict[str, Any]) -> dict[str, Any]:
        out = {**outputs, **recorded}
        recorded.clear()
        return out

    model.register_forward_hook(merge)
    model.tap_kinds = {**getattr(model, "tap_kinds", {}), **{n: s.kind for n, s in hooks.items()}}
