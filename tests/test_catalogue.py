"""The describing commands start without torch (issue 57, item 17): ``distilkit list`` and ``distilkit schema``
print from the catalogue (``distilkit.catalogue``), which is recomputed when the code or a plugin changes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

PROBE = ("import sys; from distilkit.cli import main; code = main(sys.argv[1:]); "
         "print('TORCH' if 'torch' in sys.modules else 'NO-TORCH', file=sys.stderr); sys.exit(code)")


def _cli(cache: Path, *args: str, pythonpath: str | None = None, catalogue: str = "1") -> subprocess.CompletedProcess:
    env = {**os.environ, "DISTILKIT_CACHE": str(cache), "DISTILKIT_CATALOGUE": catalogue, "COLUMNS": "200"}
    if pythonpath:
        env["PYTHONPATH"] = os.pathsep.join([pythonpath, *filter(None, [env.get("PYTHONPATH")])])
    out = subprocess.run([sys.executable, "-c", PROBE, *args], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out


def _plugin(root: Path) -> Path:
    """A user's plugin as an installed distribution would be (a dist-info with its entry point) on a path."""
    pkg = root / "catalogue_plugin"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(
        "from distilkit.registry import CONNECTORS\n"
        "def register():\n"
        "    CONNECTORS.add('catalogue-probe', object, description='a connector only this test registers')\n",
        encoding="utf-8")
    info = root / "catalogue_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: catalogue-plugin\nVersion: 0.1\n", encoding="utf-8")
    (info / "entry_points.txt").write_text("[distilkit.plugins]\nprobe = catalogue_plugin:register\n", encoding="utf-8")
    return root


def test_list_and_schema_print_the_same_from_the_catalogue_without_importing_torch(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    for args in (["list"], ["schema"], ["list", "objectives", "--markdown"]):
        live = _cli(cache, *args, catalogue="0")
        first = _cli(cache, *args)
        again = _cli(cache, *args)
        assert live.stdout == first.stdout == again.stdout, args
        assert "TORCH" in live.stderr.split() and "NO-TORCH" in again.stderr.split(), (args, again.stderr)
    schema = json.loads(_cli(cache, "schema").stdout)
    assert schema["title"] == "distilkit recipe"
    assert sorted(p.name for p in (cache / "catalogue").iterdir()) == [
        "list-objectives-markdown.json", "list.json", "schema.json"]


def test_a_plugin_installed_after_the_catalogue_was_written_is_listed(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    before = _cli(cache, "list", "connectors")
    assert "catalogue-probe" not in before.stdout
    after = _cli(cache, "list", "connectors", pythonpath=str(_plugin(tmp_path / "site")))
    assert "catalogue-probe" in after.stdout and "TORCH" in after.stderr.split()  # recomputed: the entry points changed
    assert "catalogue-probe" in _cli(cache, "list", "connectors", pythonpath=str(tmp_path / "site")).stdout


def test_a_changed_fingerprint_recomputes_and_an_unwritable_cache_is_passed_over(tmp_path: Path,
                                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from distilkit import catalogue

    monkeypatch.setenv("DISTILKIT_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv(catalogue.ENV, "1")
    calls: list[int] = []
    keys = iter(["a", "a", "b"])
    monkeypatch.setattr(catalogue, "fingerprint", lambda: next(keys))
    for _ in range(3):
        assert catalogue.cached("probe", lambda: calls.append(1) or {"n": len(calls)}) == {"n": len(calls)}
    assert len(calls) == 2  # computed for "a", read for "a", computed again for "b"
    (tmp_path / "ro").write_text("a file where the cache's folder would be", encoding="utf-8")
    monkeypatch.setenv("DISTILKIT_CACHE", str(tmp_path / "ro"))
    monkeypatch.setattr(catalogue, "fingerprint", lambda: "c")
    assert catalogue.cached("probe", lambda: {"n": 7}) == {"n": 7}
