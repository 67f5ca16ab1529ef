"""The house's layering (docs/development/architecture.md): import-linter's contracts in pyproject.toml hold, they
fail — naming the import chain — when an upward import is added, no module of distilkit or its adapters is part of an
import circle, every top-level module of distilkit sits in a layer, and a module longer than 400 lines says why in
its docstring."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import grimp

from conftest import ROOT

try:
    import tomllib
except ImportError:  # Python 3.10
    from pip._vendor import tomli as tomllib

PACKAGES = ("distilkit", "distilkit_adapters")


def lint(root: Path) -> subprocess.CompletedProcess[str]:
    """``lint-imports`` on the packages under ``root`` (their copy first on the path), with ``root``'s pyproject.toml."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    code = "import sys; from importlinter.cli import lint_imports; sys.exit(lint_imports(no_cache=True, no_logo=True))"
    return subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=300)


def test_the_import_contracts_hold() -> None:
    done = lint(ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert "0 broken" in done.stdout and f"{len(contracts)} kept" in done.stdout, done.stdout


def test_pairing_uses_only_its_lower_rooms(tmp_path: Path) -> None:
    """The pairing contract: what a model offers (``facts``) may not read which objective fits (``fit``)."""
    for name in PACKAGES:
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    facts = tmp_path / "distilkit" / "pairing" / "facts.py"
    facts.write_text(facts.read_text().replace("from __future__ import annotations\n",
                                               "from __future__ import annotations\n\nimport distilkit.pairing.fit\n",
                                               1))
    done = lint(tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "pairing" in done.stdout and "BROKEN" in done.stdout
    assert "distilkit.pairing.facts is not allowed to import distilkit.pairing.fit" in done.stdout


def test_an_upward_import_breaks_the_layers_with_its_chain_named(tmp_path: Path) -> None:
    for name in PACKAGES:
        shutil.copytree(ROOT / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path)
    batch = tmp_path / "distilkit" / "data" / "batch.py"
    text = batch.read_text()
    batch.write_text(text.replace("from __future__ import annotations\n",
                                  "from __future__ import annotations\n\nimport distilkit.engine.train.trainer\n", 1))
    done = lint(tmp_path)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "distilkit is a stack of layers BROKEN" in done.stdout
    assert "distilkit.data is not allowed to import distilkit.engine" in done.stdout
    assert "distilkit.data.batch -> distilkit.engine.train.trainer" in done.stdout


def strongly_connected(edges: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's strongly connected components of more than one module (the import circles), iteratively."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[set[str]] = []
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                if len(component) > 1:
                    out.append(component)
    return out


def test_strongly_connected_finds_a_circle() -> None:
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
    assert strongly_connected({"a": {"b"}, "b": set()}) == []


def test_no_module_is_part_of_an_import_circle() -> None:
    graph = grimp.build_graph(*PACKAGES, include_external_packages=False)
    edges = {m: set(graph.find_modules_directly_imported_by(m)) for m in graph.modules}
    circles = strongly_connected(edges)
    assert not circles, [sorted(c) for c in circles]


def test_every_top_level_module_sits_in_a_layer() -> None:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    layers = next(c for c in config if c["id"] == "layers")["layers"]
    named = {part.strip() for layer in layers for part in layer.split("|")}
    graph = grimp.build_graph("distilkit", include_external_packages=False)
    children = {m.split(".")[1] for m in graph.find_children("distilkit")} - {"__main__"}
    assert children == named, f"not in a layer: {sorted(children - named)}; no such module: {sorted(named - children)}"


def test_a_module_over_400_lines_says_why() -> None:
    long = []
    for path in sorted((ROOT / "distilkit").rglob("*.py")):
        text = path.read_text()
        if text.count("\n") > 400 and "Why one module:" not in (ast.get_docstring(ast.parse(text)) or ""):
            long.append(f"{path.relative_to(ROOT)} ({text.count(chr(10))} lines)")
    assert not long, long
