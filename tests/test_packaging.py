"""What a user installs is the built wheel: it must hold every module of the source tree (a package folder left
out of discovery, or one without ``__init__.py``, would install a distilkit that fails after training), the
console script and the entry point of the built-in adapters. CI also installs the wheel into a clean environment
and runs a recipe outside the checkout (``.ci/wheel-smoke``)."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from conftest import ROOT

PACKAGES = ("distilkit", "distilkit_adapters")


def _tree_files() -> set[str]:
    """Every module (and typed marker) of the packages in the checkout, as paths inside a wheel."""
    out: set[str] = set()
    for top in PACKAGES:
        for path in (ROOT / top).rglob("*"):
            if path.suffix == ".py" or path.name == "py.typed":
                if "__pycache__" not in path.parts:
                    out.add(path.relative_to(ROOT).as_posix())
    return out


def test_every_folder_with_modules_is_a_package() -> None:
    missing = sorted({p.parent.relative_to(ROOT).as_posix() for top in PACKAGES for p in (ROOT / top).rglob("*.py")
                      if "__pycache__" not in p.parts and not (p.parent / "__init__.py").is_file()})
    assert not missing, f"folders with modules but no __init__.py (left out of the wheel): {missing}"


def test_the_built_wheel_holds_every_module_the_script_and_the_builtin_entry_point(tmp_path: Path) -> None:
    src = tmp_path / "src"  # a copy of what the build reads, so no build/ or egg-info lands in the checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for top in PACKAGES:
        shutil.copytree(ROOT / top, src / top, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path / "dist"
    out.mkdir()
    # the PEP 517 hook pip calls, with the setuptools of the test environment (no download)
    done = subprocess.run([sys.executable, "-c", f"from setuptools import build_meta as b; print(b.build_wheel({str(out)!r}))"],
                          cwd=src, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    wheel = out / done.stdout.strip().splitlines()[-1]
    with zipfile.ZipFile(wheel) as z:
        names = set(z.namelist())
        info = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        entry_points = z.read(info).decode()
    lacking = sorted(_tree_files() - names)
    assert not lacking, f"the wheel lacks {lacking}"
    assert "distilkit/sweep/runner.py" in names and "distilkit/report/run.py" in names  # the two that were lost
    eps = configparser.ConfigParser()
    eps.read_string(entry_points)
    assert eps["console_scripts"]["distilkit"] == "distilkit.cli:main"
    assert eps["distilkit.plugins"]["builtin-adapters"] == "distilkit_adapters:register"
    assert not any(n.startswith(("tests/", "recipes/", "docs/")) for n in names)
