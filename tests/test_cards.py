"""Checking a recipe reads cards, not implementations (issue 57, item 17): ``distilkit validate --static`` and
``distilkit sweep --plan`` start without torch, and what a card declares is what the implementation runs with."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from distilkit.cards.base import AdapterCard, MetricCard, TermCard
from distilkit.registry import ALL_REGISTRIES, load_plugins

ROOT = Path(__file__).resolve().parents[1]
PROBE = ("import sys; from distilkit.cli import main; code = main(sys.argv[1:]); "
         "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH', file=sys.stderr); sys.exit(code)")
# the synthetic-data recipes a new user validates first (the paper recipes read real folders and weights files)
RECIPES = sorted(p.name for p in (ROOT / "recipes").glob("*.yaml") if p.name != "semantickitti_scpnet.yaml")
SWEEPS = sorted(p.name for p in (ROOT / "recipes" / "sweeps").glob("*.yaml"))


def _cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "DISTILKIT_CACHE": str(tmp_path / "cache"), "COLUMNS": "200"}
    out = subprocess.run([sys.executable, "-c", PROBE, *args], env=env, capture_output=True, text=True, timeout=300,
                         cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return out


@pytest.mark.parametrize("recipe", RECIPES)
def test_validate_static_imports_no_torch(tmp_path: Path, recipe: str) -> None:
    out = _cli(tmp_path, "validate", "--static", f"recipes/{recipe}")
    assert ": ok — " in out.stdout
    assert out.stderr.strip().splitlines()[-1] == "NO-TORCH", out.stderr


@pytest.mark.parametrize("sweep", SWEEPS)
def test_sweep_plan_imports_no_torch(tmp_path: Path, sweep: str) -> None:
    out = _cli(tmp_path, "sweep", f"recipes/sweeps/{sweep}", "--plan", "--output", str(tmp_path / "runs"))
    assert out.stdout.count("distilkit run ") >= 2
    assert out.stderr.strip().splitlines()[-1] == "NO-TORCH", out.stderr


def _builtin_entries() -> list[tuple[str, object]]:
    load_plugins()
    return [(f"{kind}:{e.name}", e) for kind, reg in ALL_REGISTRIES.items() for e in reg
            if e.impl and (e.impl.startswith("distilkit.") or e.impl.startswith("distilkit_adapters."))]


def test_every_builtin_component_is_declared_with_its_implementation_named() -> None:
    load_plugins()
    eager = [f"{kind}:{e.name} ({getattr(e.card, '__module__', '?')})" for kind, reg in ALL_REGISTRIES.items()
             for e in reg if not e.impl and str(getattr(e.card, "__module__", "")).split(".")[0]
             in ("distilkit", "distilkit_adapters")]
    assert not eager, f"registered eagerly (importing them imports torch): {eager}"


CONTRACTS = (AdapterCard, TermCard, MetricCard)


@pytest.mark.parametrize("key,entry", _builtin_entries(), ids=[k for k, _ in _builtin_entries()])
def test_what_a_card_declares_is_what_its_implementation_runs_with(key: str, entry: object) -> None:
    card, obj = entry.card, entry.obj  # type: ignore[attr-defined]
    if card is None:  # a component described by its metadata (a dataset's builder, an optimizer)
        assert callable(obj)
        return
    assert isinstance(obj, type) and issubclass(obj, card), f"{key}: {obj} does not subclass its card {card}"
    contract = next(c for c in CONTRACTS if issubclass(card, c))
    declared = {n for c in card.__mro__ if c is not object and issubclass(c, contract) for n in vars(c)
                if not n.startswith("__")}
    overridden = sorted(n for klass in obj.__mro__[:obj.__mro__.index(card)] for n in vars(klass) if n in declared)
    assert not overridden, (f"{key}: {obj.__qualname__} redefines {overridden}, which its card declares: a recipe "
                            "would be checked (and a stage identified) by other values than the ones that run")
