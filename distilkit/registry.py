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


_LAZY: dict[Any, str] = {}  # a declared card -> "module:attr" of its implementation
_LOADED: dict[str, Any] = {}  # "module:attr" -> the implementation, once imported


def _load(impl: str, card: Any, name: str) -> Any:
    """The implementation ``module:attr`` names, imported once; a class must subclass its card."""
    if impl not in _LOADED:
        module, _, attr = impl.partition(":")
        try:
            obj = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as exc:
            raise PluginError(f"{name!r}: its implementation {impl} cannot be imported: {type(exc).__name__}: "
                              f"{exc}") from exc
        if isinstance(card, type) and not (isinstance(obj, type) and issubclass(obj, card)):
            raise PluginError(f"{name!r}: its implementation {impl} is not a subclass of its card "
                              f"{card.__module__}.{card.__qualname__}")
        _LOADED[impl] = obj
    return _LOADED[impl]


def implementation(card: Any) -> Any:
    """What a card stands for: the implementation it was declared with (imported now, once), else the card itself
    (a component registered with :meth:`Registry.add` is its own card)."""
    impl = _LAZY.get(card) if _hashable(card) else None
    return card if impl is None else _load(impl, card, getattr(card, "__name__", impl))


def _hashable(obj: Any) -> bool:
    try:
        hash(obj)
    except TypeError:
        return False
    return True


class Lazy:
    """A callable named by ``"module:attr"``, imported the first time it is called: a declared component's ``meta``
    that only running needs (a dataset's collate, its memory probe) without importing it to describe the component.
    Two lazies of the same target are equal, so a component declared twice with the same metadata is one."""

    __slots__ = ("target",)

    def __init__(self, target: str) -> None:
        if ":" not in target:
            raise ValueError(f"a lazy callable is named 'module:attr', got {target!r}")
        self.target = target

    def load(self) -> Any:
        return _load(self.target, None, self.target)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.load()(*args, **kwargs)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Lazy) and other.target == self.target

    def __hash__(self) -> int:
        return hash(self.target)

    def __repr__(self) -> str:
        return f"Lazy({self.target!r})"


def lazy(target: str) -> Lazy:
    """A callable imported from ``"module:attr"`` the first time it is called (see :class:`Lazy`)."""
    return Lazy(target)


@dataclass(frozen=True)
class Entry(Generic[T]):
    """A registered component and its metadata.

    ``card`` is what describing and checking a recipe read (a component's parameters, taps, roles, declared
    without importing torch); ``obj`` is the component itself. A component registered with :meth:`Registry.add` is
    its own card; one registered with :meth:`Registry.declare` is imported from ``impl`` the first time ``obj`` is
    read, so that ``distilkit validate --static`` and ``sweep --plan`` never import what they do not run."""

    name: str
    card: Any
    description: str
    paper: str = ""
    consumes: tuple[str, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)
    impl: str = ""  # "module:attr" of the implementation ("": the card is the component)

    @property
    def obj(self) -> T:
        return self.card if not self.impl else _load(self.impl, self.card, self.name)

    @property
    def loaded(self) -> bool:
        """Whether ``obj`` can be read without importing anything."""
        return not self.impl or self.impl in _LOADED


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
        """Register ``obj`` (the component itself, already imported: a plug-in's way) as ``name``, with the
        one-line ``description`` ``distilkit list`` shows, the ``paper`` it comes from, the tap kinds it
        ``consumes`` and any ``meta`` (an objective's ``default_weight``); ``override`` replaces an entry of that
        name. Returns ``obj``, so that it can decorate a class (:meth:`register`)."""
        self._put(Entry(name, obj, description.strip(), paper, tuple(consumes), dict(meta)), override)
        return obj

    def declare(
        self,
        name: str,
        impl: str,
        *,
        card: Any = None,
        description: str,
        paper: str = "",
        consumes: tuple[str, ...] | list[str] = (),
        override: bool = False,
        **meta: Any,
    ) -> None:
        """Register ``name`` without importing it: ``impl`` ("module:attr") is imported the first time the
        component itself is used; until then ``card`` (a class the implementation subclasses, declaring what a
        recipe is checked against: its ``Params``, taps, roles) and ``meta`` stand for it. ``card=None``: the
        component is used only through ``meta`` until it runs (a dataset's builder, an optimizer)."""
        if ":" not in impl:
            raise ValueError(f"{self.kind} {name!r}: impl must be 'module:attr', got {impl!r}")
        if card is not None:
            _LAZY[card] = impl
        self._put(Entry(name, card, description.strip(), paper, tuple(consumes), dict(meta), impl), override)

    def _put(self, entry: Entry[T], override: bool) -> None:
        name = entry.name
        if not name or not isinstance(name, str):
            raise ValueError(f"{self.kind} name must be a non-empty string, got {name!r}")
        old = self._entries.get(name)
        if old is not None and not override and (old.card, old.impl) != (entry.card, entry.impl):
            raise ValueError(f"{self.kind} {name!r} is already registered (pass override=True to replace it)")
        self._entries[name] = entry

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

    def card(self, name: str) -> Any:
        """What checking a recipe reads of ``name`` (its card), without importing its implementation."""
        return self.entry(name).card

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

_BUILTIN_MODULES = (  # the cards: torch-free declarations, each component imported when it runs
    "distilkit.cards.objectives",
    "distilkit.cards.connectors",
    "distilkit.cards.task_losses",
    "distilkit.cards.metrics",
    "distilkit.cards.optim",
    "distilkit.cards.recorders",
    "distilkit.cards.datasets",
    "distilkit.cards.trackers",
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
