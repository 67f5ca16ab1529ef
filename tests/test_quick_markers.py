"""The markers of a quick run (`-m "not slow and not network and not processes"`, README) name files that exist and
are registered, so that a renamed file is not silently moved into the quick run."""

from __future__ import annotations

import tomllib
from pathlib import Path

from conftest import BY_FILE, ROOT


def test_the_quick_runs_markers_name_files_that_exist_and_are_registered() -> None:
    here = Path(__file__).resolve().parent
    for marker, files in BY_FILE.items():
        assert files and all((here / f).is_file() for f in files), (marker, sorted(f for f in files
                                                                                   if not (here / f).is_file()))
    registered = {m.split(":")[0] for m in
                  tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]["markers"]}
    assert set(BY_FILE) <= registered
    assert not set(BY_FILE["network"]) & set(BY_FILE["processes"])  # one reason each
