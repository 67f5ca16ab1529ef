"""The worked example of docs/tutorials/your-own-model.md, loaded through a real entry point."""

from __future__ import annotations

import sys

import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT
from distilkit import registry
from distilkit.engine.train.pipeline import Pipeline
from distilkit.recipe import recipe_from_dict

EXAMPLE = ROOT / "docs" / "examples" / "tiny_adapter"


def test_entry_point_plugin_runs_its_recipe(tmp_path, monkeypatch) -> None:
    """The worked example, installed as a distribution with an entry point, registers tiny-ssc and its recipe trains
    the user's model with DSKD (a step a stage: what is asserted is that the plugin loads and its stage finishes)."""
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
    try:
        _run_the_examples_recipe(tmp_path)
    finally:  # this process's registries as they were: a later test lists the adapters
        registry.ADAPTERS.remove("tiny-ssc")
        sys.modules.pop("tiny_adapter", None)


def _run_the_examples_recipe(tmp_path) -> None:
    recipe = yaml.safe_load((EXAMPLE / "recipe.yaml").read_text())
    for stage in recipe["stages"].values():  # about loading a plugin: the CPU, not the recipe's auto (a GPU)
        stage.setdefault("train", {}).update(steps=1, device="cpu")
    recipe["data"]["params"]["num_test"] = 1  # not the default 32 test scenes, scored twice a stage
    results = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    mine = results[-1]
    assert mine.summary["adapter"] == "tiny-ssc" and mine.summary["objectives"] == ["dskd×100"]
    assert mine.summary["status"] == "finished"  # (also the guide's run: its code is this module's, asserted below)
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


def test_a_plugin_registers_a_connector_and_a_schedule_and_a_recipe_uses_both(tmp_path, monkeypatch) -> None:
    """Through a real entry point: a plugin package adds a connector (a gated projection) and a schedule
    (linear decay); a recipe names both; the connector trains with the student and the rate follows the schedule."""
    import json

    import torch

    from conftest import tiny_recipe
    from distilkit.weights import load_checkpoint

    site = tmp_path / "site"
    site.mkdir()
    (site / "my_kd_extras.py").write_text(
        "import torch\n"
        "from torch import nn\n"
        "from distilkit.engine.train.optim import NoParams\n"
        "from distilkit.registry import CONNECTORS, SCHEDULES\n\n"
        "class Gated(nn.Module):\n"
        "    def __init__(self, cs, ct):\n"
        "        super().__init__()\n"
        "        self.lin, self.gate = nn.Linear(cs, ct), nn.Parameter(torch.ones(ct))\n"
        "    def forward(self, x):\n"
        "        return self.lin(x) * self.gate\n\n"
        "def register():\n"
        "    CONNECTORS.add('gated', lambda cs, ct, dims: Gated(cs, ct), description='gated', paper='plugin')\n"
        "    SCHEDULES.add('linear_decay', lambda step, total, p: 1 - step / total, description='decay',\n"
        "                  paper='plugin', params=NoParams)\n")
    _fake_distribution(site, "my-kd-extras", "extras = my_kd_extras:register")
    monkeypatch.syspath_prepend(str(site))
    registry.load_plugins(force=True)
    try:
        r = tiny_recipe(steps=4)
        r["stages"]["teacher"]["train"] = {**r["stages"]["teacher"]["train"], "steps": 1, "eval_every": 1}
        student = r["stages"]["student"]  # 4 steps: the schedule's rates; the teacher's steps do not matter
        student["distill"] = [{"name": "dskd", "weight": 10.0, "connector": "gated"}]
        student["optimizer"] = {"lr": 0.01, "schedule": {"name": "linear_decay"}}
        teacher_run, student_run = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).run()
        ckpt = load_checkpoint(student_run.run_dir / "checkpoints" / "last.pt")
        gate = next(v for k, v in ckpt["connectors"].items() if k.endswith("gate"))
        assert not torch.equal(gate, torch.ones_like(gate))  # trained with the student
        lrs = [json.loads(x)["lr"] for x in (student_run.run_dir / "metrics.jsonl").read_text().splitlines()
               if "lr" in json.loads(x)]
        assert lrs == [0.01, 0.0075, 0.005, 0.0025]
    finally:
        monkeypatch.undo()
        registry.load_plugins(force=True)
        registry.CONNECTORS.remove("gated")
        registry.SCHEDULES.remove("linear_decay")


def _guide_blocks(kind: str) -> list[str]:
    import re

    return re.findall(rf"```{kind}\n(.*?)```", (ROOT / "docs" / "tutorials" / "your-own-model.md").read_text(), re.S)


def test_the_plugin_guide_runs_as_written(tmp_path, monkeypatch) -> None:
    """docs/tutorials/your-own-model.md's §1-2 code blocks, written out as a module exactly as they stand, register an
    adapter; the worked example's files are that same code (after a docstring) and §3's recipe — which
    test_entry_point_plugin_runs_its_recipe trains through an entry point (its stages finish), so it is not trained
    a second time here."""
    import importlib

    code = _guide_blocks("python")[0] + "\n\n" + _guide_blocks("python")[1]
    (tmp_path / "guide_adapter.py").write_text(code)
    example = (EXAMPLE / "tiny_adapter.py").read_text()
    assert example.endswith(code) and example[: -len(code)].lstrip().startswith('"""')  # only a docstring before
    recipe = yaml.safe_load(_guide_blocks("yaml")[0])
    assert recipe == yaml.safe_load((EXAMPLE / "recipe.yaml").read_text()) and recipe["name"]
    monkeypatch.syspath_prepend(str(tmp_path))
    entries = registry.ADAPTERS._entries  # noqa: SLF001
    before = entries.pop("tiny-ssc", None)  # another test's registration, put back afterwards
    try:
        module = importlib.import_module("guide_adapter")
        module.register()
        assert registry.ADAPTERS.get("tiny-ssc") is module.TinySSC
        assert {s["model"]["adapter"] for s in recipe["stages"].values()} >= {"tiny-ssc"}  # the recipe trains it
    finally:
        entries.pop("tiny-ssc", None)
        if before is not None:
            entries["tiny-ssc"] = before
