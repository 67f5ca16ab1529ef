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

from pydantic import BaseModel, ConfigDict

from distilkit.errors import PluginError, UnknownNameError


class NoParams(BaseModel):
    """The parameters of a registered component that takes none (a recipe may give ``params: {}`` only)."""

    model_config = ConfigDict(extra="forbid")

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
        self._aliases: dict[str, tuple[str, bool]] = {}  # other name -> (registered name, deprecated)

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

    def alias(self, other: str, name: str, deprecated: bool = False) -> None:
        """Let ``other`` name the component registered as ``name``. Names are part of stage identities, so a
        recipe that uses an alias resolves (and hashes) to ``name``; a ``deprecated`` alias also warns, so that a
        component can be renamed without breaking recipes or retraining finished stages."""
        if other in self._entries:
            raise ValueError(f"{self.kind} {other!r} is registered itself; it cannot also be an alias")
        self._aliases[other] = (name, deprecated)

    def canonical(self, name: str) -> str:
        """The registered name ``name`` stands for (itself, or the target of an alias; a deprecated alias warns)."""
        if name in self._entries or name not in self._aliases:
            return name
        target, deprecated = self._aliases[name]
        if deprecated:
            warnings.warn(f"{self.kind} {name!r} is deprecated: use {target!r} (the same component; stages keep "
                          "their identity)", FutureWarning, stacklevel=3)
        return target

    def aliases_of(self, name: str) -> list[str]:
        return sorted(a for a, (target, _) in self._aliases.items() if target == name)

    def register(self, name: str, **kwargs: Any) -> Callable[[T], T]:
        """Decorator form of :meth:`add`."""

        def deco(obj: T) -> T:
            return self.add(name, obj, **kwargs)

        return deco

    def remove(self, name: str) -> None:
        """Unregister ``name`` and its aliases (tests and notebooks that register temporary components)."""
        self._entries.pop(name, None)
        self._aliases = {a: t for a, t in self._aliases.items() if a != name and t[0] != name}

    def entry(self, name: str) -> Entry[T]:
        """The component registered as ``name`` or as the target of the alias ``name`` (its ``name`` is canonical)."""
        load_plugins()
        try:
            return self._entries[self.canonical(name)]
        except KeyError:
            raise UnknownNameError(self.unknown_message(name)) from None

    def get(self, name: str) -> T:
        return self.entry(name).obj

    def registered(self, name: str) -> T | None:
        """The component ``name`` names if it is registered in this process so far (built-in components, plugins
        or a script's own ``add``), without loading the plugins; else None."""
        target = self._aliases.get(name, (name, False))[0]
        entry = self._entries.get(target)
        return entry.obj if entry is not None else None

    def unknown_message(self, name: object) -> str:
        close = difflib.get_close_matches(str(name), [*self._entries, *self._aliases], n=3, cutoff=0.6)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        known = ", ".join(sorted(self._entries)) or "none"
        broken = "".join(f"; {msg}" for msg in plugin_errors)  # the component may live in a plugin that failed
        return f"unknown {self.kind} {name!r}{hint} (known: {known}){broken}"

    def names(self, pattern: str | None = None) -> list[str]:
        load_plugins()
        names = sorted(self._entries)
        return [n for n in names if pattern is None or fnmatch.fnmatch(n, pattern)]

    def __contains__(self, name: object) -> bool:
        load_plugins()
        return name in self._entries or name in self._aliases

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

OPTIMIZERS: Registry[Any] = Registry("optimizer")
SCHEDULES: Registry[Any] = Registry("schedule")
CONNECTORS: Registry[Any] = Registry("connector")
HOOKS: Registry[Any] = Registry("hook")
RECORDERS: Registry[Any] = Registry("recorder")

ALL_REGISTRIES = {"adapters": ADAPTERS, "objectives": OBJECTIVES, "task losses": TASK_LOSSES,
                  "datasets": DATASETS, "metrics": METRICS, "optimizers": OPTIMIZERS, "schedules": SCHEDULES,
                  "connectors": CONNECTORS, "hooks": HOOKS, "recorders": RECORDERS}

_BUILTIN_MODULES = (
    "distilkit.objectives",
    "distilkit.losses.task",
    "distilkit.data.datasets",
    "distilkit.metrics.registered",
    "distilkit.engine.train.optim",
    "distilkit.engine.train.tensorboard",
    "distilkit.engine.train.trackers",
    "distilkit.engine.assemble.recorders",
)
_loaded = False
_loading = False
plugin_errors: list[str] = []
BUILTIN_DISTRIBUTION = "distilkit"  # entry points of distilkit's own distribution are the built-in adapters


def _is_builtin(ep: Any) -> bool:
    """Whether an entry point belongs to distilkit itself (its built-in adapters) rather than a user's package."""
    dist = getattr(ep, "dist", None)
    name = getattr(dist, "name", None) or (getattr(dist, "metadata", None) or {}).get("Name")
    if name is not None:
        return str(name).lower() == BUILTIN_DISTRIBUTION
    return str(ep.value).split(":")[0].split(".")[0] == "distilkit_adapters"


def _failure(ep: Any, exc: BaseException) -> str:
    """``plugin 'name' (module:attr) failed to load: Type: message (at file:line)``, the line where it failed."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    where = f" (at {frames[-1].filename}:{frames[-1].lineno})" if frames else ""
    return f"plugin {ep.name!r} ({ep.value}) failed to load: {type(exc).__name__}: {exc}{where}"


def plugins_loaded() -> bool:
    """Whether the built-in components and the plugins are loaded in this process."""
    return _loaded


def load_plugins(force: bool = False) -> None:
    """Import the built-in components and every ``distilkit.plugins`` entry point (once;
    ``force=True`` looks for entry points again, e.g. after a package was installed).

    distilkit's own adapters failing to load is an error (:class:`~distilkit.errors.PluginError`: the
    installation is broken). A user's plugin that fails is named with its entry point and the cause in a
    warning, and again in the error of any lookup of a name that is not found (it may be that plugin's)."""
    global _loaded, _loading
    if _loading or (_loaded and not force):
        return
    _loading, _loaded = True, False  # a load that fails leaves it unloaded: the next lookup raises again
    try:
        for mod in _BUILTIN_MODULES:
            importlib.import_module(mod)
        from importlib.metadata import entry_points

        plugin_errors.clear()
        for ep in entry_points(group=ENTRY_POINT_GROUP):
            try:
                target = ep.load()
                if callable(target):
                    target()
            except Exception as exc:
                msg = _failure(ep, exc)
                if _is_builtin(ep):  # distilkit's own adapters: the installation is broken
                    raise PluginError(f"distilkit's built-in {msg}; the installation is incomplete or broken: "
                                      "reinstall distilkit") from exc
                plugin_errors.append(msg)  # a user's plugin must not break distilkit
                warnings.warn(msg, RuntimeWarning, stacklevel=2)
        _loaded = True
    finally:
        _loading = False
