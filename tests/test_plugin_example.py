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
