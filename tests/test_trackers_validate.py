"""What ``validate`` says about a recipe's trackers before any stage starts, without the network and without
importing a tracker's library: a tracker given twice, MLflow's store needs (SQLAlchemy for a database store,
``MLFLOW_ALLOW_FILE_STORE=true`` for a file store), W&B's login for an online run; and the schema's list of the
trackers with their parameters."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from conftest import tiny_recipe
from distilkit.errors import RecipeError


@pytest.fixture
def bare_env(tmp_path: Path, monkeypatch) -> Path:
    """No tracker variable, no W&B login anywhere (an empty netrc, a home without settings), the working folder
    an empty one."""
    for key in [k for k in os.environ if k.startswith(("WANDB_", "MLFLOW_", "TRACKIO_"))]:
        monkeypatch.delenv(key)
    (tmp_path / "home").mkdir()
    (tmp_path / "netrc").write_text("")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("NETRC", str(tmp_path / "netrc"))
    monkeypatch.setenv("WANDB_CONFIG_DIR", str(tmp_path / "home" / "wandb-config"))
    (tmp_path / "work").mkdir()
    monkeypatch.chdir(tmp_path / "work")
    return tmp_path


def problems(trackers: list) -> str:
    """What validating a tiny recipe with ``trackers`` says ("" when nothing)."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    try:
        resolve(recipe_from_dict({**tiny_recipe(steps=1, distill=False), "trackers": trackers}))
    except RecipeError as exc:
        return str(exc)
    return ""


@pytest.mark.parametrize("trackers, twice", [(["mlflow", {"mlflow": {"experiment": "other"}}], "mlflow"),
                                             (["trackio", "tensorboard", "trackio"], "trackio"),
                                             ([{"wandb": {"mode": "offline"}}, {"wandb": None}], "wandb")])
def test_a_tracker_given_twice_is_refused_in_one_line(trackers: list, twice: str, bare_env) -> None:
    text = problems(trackers)
    assert f"trackers[{len(trackers) - 1}]: {twice} is given twice" in text, text
    assert len(text.splitlines()) == 1


def test_mlflow_is_checked_for_what_its_tracking_uri_needs(bare_env, monkeypatch) -> None:
    """MLflow's default store (no URI anywhere, no ./mlruns) is SQLite, which needs SQLAlchemy and Alembic (not in
    mlflow-skinny); a file store needs MLFLOW_ALLOW_FILE_STORE=true (MLflow 3 refuses it otherwise); a server
    needs neither."""
    monkeypatch.setitem(sys.modules, "sqlalchemy", None)  # as if only mlflow-skinny were installed
    text = problems(["mlflow"])
    assert "trackers[0]: MLflow's store sqlite:///mlflow.db (MLflow's default) needs sqlalchemy" in text, text
    assert "pip install 'distilkit[mlflow]'" in text
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "mlruns")
    text = problems([{"mlflow": {"tracking_uri": "sqlite:///x.db"}}])  # the variable wins over the recipe
    assert "trackers[0]: MLflow's file store mlruns needs MLFLOW_ALLOW_FILE_STORE=true" in text, text
    monkeypatch.setenv("MLFLOW_ALLOW_FILE_STORE", "true")
    assert problems(["mlflow"]) == ""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://mlflow.example:5000")
    monkeypatch.delenv("MLFLOW_ALLOW_FILE_STORE")
    assert problems(["mlflow"]) == ""


def test_wandb_online_without_a_login_is_one_line_from_validate(bare_env, monkeypatch) -> None:
    text = problems(["wandb"])
    assert text.splitlines() == [f"recipe: trackers[0]: the wandb tracker logs online but finds no W&B login for "
                                 f"api.wandb.ai (WANDB_API_KEY, {bare_env / 'netrc'}, wandb's settings): run `wandb "
                                 f"login`, or log offline with {{wandb: {{mode: offline}}}} and upload with `wandb "
                                 f"sync` later"], text
    assert problems([{"wandb": {"mode": "offline"}}]) == problems([{"wandb": {"mode": "disabled"}}]) == ""
    monkeypatch.setenv("WANDB_MODE", "offline")  # the variable wins over the recipe
    assert problems([{"wandb": {"mode": "online"}}]) == ""
    monkeypatch.delenv("WANDB_MODE")
    (bare_env / "netrc").write_text("machine api.wandb.ai\n  login user\n  password " + "k" * 40 + "\n")
    assert problems(["wandb"]) == ""
    (bare_env / "netrc").write_text("")
    monkeypatch.setenv("WANDB_API_KEY", "k" * 40)
    assert problems(["wandb"]) == ""
    monkeypatch.delenv("WANDB_API_KEY")
    settings = bare_env / "home" / "wandb-config" / "settings"
    settings.parent.mkdir()
    settings.write_text("[default]\nmode = offline\n")  # `wandb offline`
    assert problems(["wandb"]) == ""


def test_the_schema_lists_the_trackers_and_their_parameters() -> None:
    from distilkit.schema_doc import recipe_json_schema, recipe_reference_markdown

    schema = json.loads(recipe_json_schema())
    items = schema["properties"]["trackers"]["items"]
    names = next(option["enum"] for option in items["anyOf"] if "enum" in option)
    assert {"tensorboard", "wandb", "mlflow", "trackio"} <= set(names)
    defs = schema["$defs"]
    assert {"tracking_uri", "experiment", "every"} <= set(defs["TrackerParams_mlflow"]["properties"])
    assert defs["TrackerParams_wandb"]["properties"]["mode"]["anyOf"][0]["enum"] == ["online", "offline", "disabled"]
    markdown = recipe_reference_markdown()
    section = markdown[markdown.index("## Trackers"):]
    for name, param in (("tensorboard", "folder"), ("wandb", "mode"), ("mlflow", "tracking_uri"),
                        ("trackio", "project")):
        assert f"### {name}" in section and f"| `{param}` |" in section[section.index(f"### {name}"):]
