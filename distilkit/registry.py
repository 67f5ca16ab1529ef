"""One generic registry for adapters, objectives, task losses, datasets and metrics.

Third-party packages plug in through the entry-point group ``distilkit.plugins``: each
entry point names a callable (called once with no arguments) or a module (imported) that
registers its components with the registries below.
"""

from __future__ import annotations

import difflib
import fnmatch
import importlib
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, Iterator, TypeVar

from distilkit.errors import UnknownNameError

T = TypeVar("T")

ENTRY_POINT_GROUP = "distilkit.plugins"


@dataclass(frozen=True)
class Entry(Generic[T]):
    """A registered component and its metadata."""

    name: str
    obj: T
    description: str
    paper: str = ""
    consumes: tuple[str, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)


class Registry(Generic[T]):
    """A name -> component catalogue that rejects duplicates and suggests close matches."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._entries: dict[str, Entry[T]] = {}

    def add(
        self,
        name: str,
        obj: T,
        *,
        description: str,
        paper: str = "",
        consumes: tuple[str, ...] | list[str] = (),
        override: bool = False,
        **meta: Any,
    ) -> T:
        if not name or not isinstance(name, str):
            raise ValueError(f"{self.kind} name must be a non-empty string, got {name!r}")
        if name in self._entries and not override and self._entries[name].obj is not obj:
            raise ValueError(f"{self.kind} {name!r} is already registered (pass override=True to replace it)")
        self._entries[name] = Entry(name, obj, description.strip(), paper, tuple(consumes), dict(meta))
        return obj

    def register(self, name: str, **kwargs: Any) -> Callable[[T], T]:
        """Decorator form of :meth:`add`."""

        def deco(obj: T) -> T:
            return self.add(name, obj, **kwargs)

        return deco

    def remove(self, name: str) -> None:
        """Unregister ``name`` (tests and notebooks that register temporary components)."""
        self._entries.pop(name, None)

    def entry(self, name: str) -> Entry[T]:
        load_plugins()
        try:
            return self._entries[name]
        except KeyError:
            raise UnknownNameError(self.unknown_message(name)) from None

    def get(self, name: str) -> T:
        return self.entry(name).obj

    def unknown_message(self, name: object) -> str:
        close = difflib.get_close_matches(str(name), list(self._entries), n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        known = ", ".join(sorted(self._entries)) or "none"
        return f"unknown {self.kind} {name!r}{hint} (known: {known})"

    def names(self, pattern: str | None = None) -> list[str]:
        load_plugins()
        names = sorted(self._entries)
        return [n for n in names if pattern is None or fnmatch.fnmatch(n, pattern)]

    def __contains__(self, name: object) -> bool:
        load_plugins()
        return name in self._entries

    def __iter__(self) -> Iterator[Entry[T]]:
        load_plugins()
        return iter([self._entries[n] for n in sorted(self._entries)])

    def __len__(self) -> int:
        load_plugins()
        return len(self._entries)


ADAPTERS: Registry[Any] = Registry("adapter")
OBJECTIVES: Registry[Any] = Registry("objective")
TASK_LOSSES: Registry[Any] = Registry("task loss")
DATASETS: Registry[Any] = Registry("dataset")
METRICS: Registry[Any] = Registry("metric")

ALL_REGISTRIES = {"adapters": ADAPTERS, "objectives": OBJECTIVES, "task losses": TASK_LOSSES,
                  "datasets": DATASETS, "metrics": METRICS}

_BUILTIN_MODULES = (
    "distilkit.objectives",
    "distilkit.losses.task",
    "distilkit.data.datasets",
    "distilkit.metrics.registered",
)
_loaded = False
_loading = False
plugin_errors: list[str] = []


def load_plugins(force: bool = False) -> None:
    """Import the built-in components and every ``distilkit.plugins`` entry point (once;
    ``force=True`` looks for entry points again, e.g. after a package was installed)."""
    global _loaded, _loading
    if _loading or (_loaded and not force):
        return
    _loading = True
    try:
        for mod in _BUILTIN_MODULES:
            importlib.import_module(mod)
        from importlib.metadata import entry_points

        for ep in entry_points(group=ENTRY_POINT_GROUP):
            try:
                target = ep.load()
                if callable(target):
                    target()
            except Exception as exc:  # a broken third-party plugin must not break distilkit
                msg = f"plugin {ep.name!r} ({ep.value}) failed to load: {exc}"
                plugin_errors.append(msg)
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
        _loaded = True
    finally:
        _loading = False
