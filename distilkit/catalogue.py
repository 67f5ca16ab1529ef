"""What the describing commands print (``distilkit list``, ``distilkit schema``), kept between processes so that they
start in a fraction of a second instead of importing torch and every component (about 3 s here).

A command's output data is computed once from the registries and written to ``$DISTILKIT_CACHE/catalogue/`` under a
fingerprint of everything it depends on: distilkit's version and the size and modification time of every module of
``distilkit`` and ``distilkit_adapters``, the ``distilkit.plugins`` entry points with their distributions' versions
and the files of their top-level packages, and the versions of Python and pydantic (which writes the schema). Any
change to those recomputes it; ``DISTILKIT_CATALOGUE=0`` never reads it.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Any, Callable

ENV = "DISTILKIT_CATALOGUE"
FORMAT = 1  # the stored file's layout


def _package_files(name: str) -> list[str]:
    """``path:size:mtime`` of every module of top-level package ``name`` (found without importing it)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return [f"{name}:missing"]
    if spec is None or spec.origin is None:
        return [f"{name}:missing"]
    origin = Path(spec.origin)
    roots = [Path(p) for p in spec.submodule_search_locations or []] or [origin]
    out = []
    for root in roots:
        for path in sorted(root.rglob("*.py")) if root.is_dir() else [root]:
            try:
                st = path.stat()
            except OSError:
                continue
            out.append(f"{path}:{st.st_size}:{st.st_mtime_ns}")
    return out


def fingerprint() -> str:
    """A hash of everything the registries' content depends on (the module's docstring lists it)."""
    from importlib import metadata

    from distilkit import __version__

    parts: list[str] = [f"format {FORMAT}", __version__, sys.version]
    for package in ("pydantic", "torch"):
        try:
            parts.append(f"{package} {metadata.version(package)}")
        except metadata.PackageNotFoundError:
            parts.append(f"{package} missing")
    parts += _package_files("distilkit") + _package_files("distilkit_adapters")
    for ep in sorted(metadata.entry_points(group="distilkit.plugins"), key=lambda e: (e.name, e.value)):
        dist = getattr(ep, "dist", None)
        parts.append(f"plugin {ep.name}={ep.value} {getattr(dist, 'name', '')} {getattr(dist, 'version', '')}")
        top = ep.value.split(":")[0].split(".")[0]
        if top not in ("distilkit", "distilkit_adapters"):
            parts += _package_files(top)
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:24]


def _path(name: str) -> Path:
    from distilkit.files import cache_root

    return cache_root() / "catalogue" / f"{name}.json"


def cached(name: str, compute: Callable[[], Any]) -> Any:
    """``compute()``'s value (JSON data), read from the catalogue when it was computed for this fingerprint, else
    computed and written there (a cache that cannot be written is passed over)."""
    if os.environ.get(ENV, "1").strip().lower() in ("0", "false", "no", "off"):
        return compute()
    key = fingerprint()
    path = _path(name)
    try:
        stored = json.loads(path.read_text(encoding="utf-8"))
        if isinstance(stored, dict) and stored.get("key") == key:
            return stored["value"]
    except (OSError, ValueError, KeyError):
        pass
    value = compute()
    try:
        from distilkit.files import atomic_write_text

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps({"key": key, "value": value}))
    except OSError:
        pass
    return value


__all__ = ["ENV", "cached", "fingerprint"]
