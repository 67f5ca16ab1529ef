"""The worked example of docs/distill-your-own-model.md, loaded through a real entry point."""

from __future__ import annotations

import sys

import yaml

from conftest import ROOT
from distilkit import registry
from distilkit.engine.pipeline import Pipeline
from distilkit.recipe import recipe_from_dict

EXAMPLE = ROOT / "docs" / "examples" / "tiny_adapter"


def test_entry_point_plugin_runs_its_recipe(tmp_path, monkeypatch) -> None:
    # an installed distribution is a *.dist-info folder on sys.path with entry_points.txt
    dist = tmp_path / "site" / "tiny_adapter-0.1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: tiny-adapter\nVersion: 0.1.0\n")
    (dist / "entry_points.txt").write_text("[distilkit.plugins]\ntiny = tiny_adapter:register\n")
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    assert "tiny-ssc" not in registry.ADAPTERS._entries
    registry.load_plugins(force=True)
    assert "tiny-ssc" in registry.ADAPTERS
    recipe = recipe_from_dict(yaml.safe_load((EXAMPLE / "recipe.yaml").read_text()))
    results = Pipeline(recipe, tmp_path / "runs", quiet=True).run()
    mine = results[-1]
    assert mine.summary["adapter"] == "tiny-ssc" and mine.summary["objectives"] == ["dskd×100"]
    assert "tiny_adapter" in sys.modules


def _fake_distribution(site, dist_name: str, ep_line: str) -> None:
    dist = site / f"{dist_name.replace('-', '_')}-0.1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist_name}\nVersion: 0.1.0\n")
    (dist / "entry_points.txt").write_text(f"[distilkit.plugins]\n{ep_line}\n")


def test_a_users_plugin_that_fails_is_named_with_its_entry_point_and_cause(tmp_path, monkeypatch) -> None:
    import pytest

    from distilkit.errors import UnknownNameError

    site = tmp_path / "site"
    (site / "broken_plugin.py").parent.mkdir(parents=True)
    (site / "broken_plugin.py").write_text("import not_a_module_anywhere\n\ndef register():\n    pass\n")
    _fake_distribution(site, "broken-plugin", "mine = broken_plugin:register")
    monkeypatch.syspath_prepend(str(site))
    try:
        with pytest.warns(RuntimeWarning, match=r"plugin 'mine' \(broken_plugin:register\) failed to load: "
                                                r"ModuleNotFoundError: No module named 'not_a_module_anywhere'"):
            registry.load_plugins(force=True)
        assert "scpnet" in registry.ADAPTERS  # distilkit itself goes on
        with pytest.raises(UnknownNameError, match=r"unknown adapter 'tiny-mine'.*plugin 'mine' \(broken_plugin"):
            registry.ADAPTERS.get("tiny-mine")
    finally:
        monkeypatch.undo()
        registry.load_plugins(force=True)
    assert not registry.plugin_errors


def test_builtin_adapters_that_fail_to_load_are_an_error_not_a_warning(monkeypatch) -> None:
    """A broken installation of distilkit itself stops with one message naming the entry point and the cause,
    instead of a warning followed by "unknown adapter 'scpnet'"."""
    import importlib.metadata as md

    import pytest

    from distilkit.cli import main
    from distilkit.errors import PluginError

    real = md.entry_points

    class Broken:
        name, value, group = "builtin-adapters", "distilkit_adapters:register", "distilkit.plugins"
        dist = type("Dist", (), {"name": "distilkit"})()

        def load(self):
            raise ImportError("cannot import name 'SCPNetAdapter' from 'distilkit_adapters.scpnet.adapter'")

    monkeypatch.setattr(md, "entry_points", lambda **kw: [Broken()] if kw.get("group") == "distilkit.plugins"
                        else real(**kw))
    try:
        with pytest.raises(PluginError, match=r"distilkit's built-in plugin 'builtin-adapters' "
                                              r"\(distilkit_adapters:register\) failed to load: ImportError: cannot "
                                              r"import name 'SCPNetAdapter'.*reinstall distilkit"):
            registry.load_plugins(force=True)
        assert main(["list", "adapters"]) == 2  # the CLI: one line, exit status 2
    finally:
        monkeypatch.undo()
        registry.load_plugins(force=True)
    assert "scpnet" in registry.ADAPTERS
