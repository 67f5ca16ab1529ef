"""The experiment trackers' declarations (torch-free): ``tensorboard``, ``wandb``, ``mlflow`` and ``trackio``, their
parameters, the check that their library is installed (looked up, never imported: :func:`missing`) and what each
needs of this machine for the recipe's parameters (MLflow's store, W&B's login), read without their libraries or the
network. The trackers themselves (:mod:`distilkit.engine.train.tensorboard`,
:mod:`distilkit.engine.train.trackers`) are imported the first time a stage runs with them."""

from __future__ import annotations

import configparser
import importlib.util
import netrc
import os
from pathlib import Path
from typing import Literal
from urllib.parse import urlparse, urlsplit

from pydantic import BaseModel, ConfigDict, Field

from distilkit.registry import HOOKS

HOST = "https://api.wandb.ai"
DATABASES = ("sqlite", "postgresql", "mysql", "mssql")  # MLflow's SQLAlchemy stores
_TRACKERS = "distilkit.engine.train.trackers"


class TrackerParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    every: int = Field(0, ge=0, description="log training values every N steps (0: as often as log_every)")


def missing(module: str, extra: str, tracker: str) -> str | None:
    """None when ``module`` can be imported (looked up, not imported), else the line that says what to install."""
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        found = False
    return None if found else (f"the {tracker} tracker needs the {module} package, which is not installed; "
                               f"pip install 'distilkit[{extra}]'")


class TensorBoardParams(TrackerParams):
    folder: str = Field("tensorboard", min_length=1, description="the event files' folder inside the run folder")


def tensorboard_missing() -> str | None:
    """None when TensorBoard's writer can be made (``torch.utils.tensorboard`` needs the tensorboard package,
    looked up, not imported), else what to install."""
    return missing("tensorboard", "tensorboard", "tensorboard")


def wandb_missing() -> str | None:
    return missing("wandb", "wandb", "wandb")


def mlflow_missing() -> str | None:
    return missing("mlflow", "mlflow", "mlflow")


def trackio_missing() -> str | None:
    return missing("trackio", "trackio", "trackio")


class WandbParams(TrackerParams):
    project: str | None = Field(None, description="W&B project (WANDB_PROJECT; default: the recipe's name, a "
                                                  "sweep's name for its runs)")
    entity: str | None = Field(None, description="W&B entity, a user or team (WANDB_ENTITY; default: W&B's)")
    mode: Literal["online", "offline", "disabled"] | None = Field(None, description="WANDB_MODE; default W&B's "
                                                                                    "(online: needs `wandb login`); "
                                                                                    "disabled logs nothing")
    dir: str | None = Field(None, description="where W&B writes its files (WANDB_DIR; default: the stage's run "
                                              "folder)")
    group: str | None = Field(None, description="run group (WANDB_RUN_GROUP; default: the sweep, else the recipe)")
    tags: list[str] = Field(default_factory=list, description="tags of every run")


def settings_files() -> dict[str, str]:
    """wandb's settings (``[default]`` of ``$WANDB_CONFIG_DIR/settings``, default ``~/.config/wandb/settings``,
    then ``./wandb/settings``, which wins), read as files: ``mode``, ``base_url``, ``api_key``."""
    out: dict[str, str] = {}
    home = Path(os.environ.get("WANDB_CONFIG_DIR") or Path("~/.config/wandb").expanduser())
    for path in (home / "settings", Path("wandb") / "settings"):
        parser = configparser.ConfigParser()
        try:
            parser.read(path, encoding="utf-8")
            out.update(parser["default"] if parser.has_section("default") else {})
        except (OSError, configparser.Error, UnicodeDecodeError):
            continue
    return out


def mode(params: WandbParams) -> str:
    """The mode a run would have here: ``WANDB_MODE``, else the recipe's, else wandb's settings, else online
    (``dryrun`` is offline, ``run`` online)."""
    value = os.environ.get("WANDB_MODE") or params.mode or settings_files().get("mode") or "online"
    return {"dryrun": "offline", "run": "online"}.get(value.strip().lower(), value.strip().lower())


def login_problem(params: WandbParams) -> str | None:
    """For an online run, one line where no W&B login is found (``WANDB_API_KEY``, ``WANDB_IDENTITY_TOKEN_FILE``,
    a netrc entry for the host, an ``api_key`` in wandb's settings), read without the network; else None."""
    if mode(params) != "online" or os.environ.get("WANDB_API_KEY") or os.environ.get("WANDB_IDENTITY_TOKEN_FILE"):
        return None
    settings = settings_files()
    host = urlsplit(os.environ.get("WANDB_BASE_URL") or settings.get("base_url") or HOST).netloc
    path = Path(os.environ.get("NETRC") or "~/.netrc").expanduser()
    if not os.environ.get("NETRC") and not path.exists() and Path("~/_netrc").expanduser().exists():
        path = Path("~/_netrc").expanduser()
    try:
        entry = netrc.netrc(str(path)).authenticators(host)
    except (OSError, netrc.NetrcParseError):
        entry = None
    if (entry and entry[2]) or settings.get("api_key"):
        return None
    return (f"the wandb tracker logs online but finds no W&B login for {host} (WANDB_API_KEY, {path}, wandb's "
            "settings): run `wandb login`, or log offline with {wandb: {mode: offline}} and upload with `wandb "
            "sync` later")


class MlflowParams(TrackerParams):
    tracking_uri: str | None = Field(None, description="where runs are recorded (MLFLOW_TRACKING_URI; default "
                                                       "MLflow's: sqlite:///mlflow.db in the working folder, which "
                                                       "needs SQLAlchemy; a file store such as ./mlruns needs "
                                                       "MLFLOW_ALLOW_FILE_STORE=true)")
    experiment: str | None = Field(None, description="experiment name (MLFLOW_EXPERIMENT_NAME; default: the "
                                                     "recipe's name, a sweep's name for its runs)")
    tags: dict[str, str] = Field(default_factory=dict, description="tags of every run")


def tracking_uri(params: MlflowParams) -> tuple[str, bool]:
    """The tracking URI a run would use here and whether it is MLflow's default (no variable, no recipe value):
    ``./mlruns`` where that holds runs, else ``sqlite:///mlflow.db`` (MLflow's rule, read without importing it)."""
    uri = os.environ.get("MLFLOW_TRACKING_URI") or params.tracking_uri
    if uri:
        return uri, False
    try:
        has_runs = any(p.name.isdigit() and (p / "meta.yaml").exists() for p in Path("mlruns").iterdir())
    except OSError:  # none (or unreadable: MLflow's rule says no runs)
        has_runs = False
    return ("./mlruns" if has_runs else "sqlite:///mlflow.db"), True


def store_problem(params: MlflowParams) -> str | None:
    """What the run's tracking URI needs that this machine lacks (one line), else None: a database store
    SQLAlchemy and Alembic (``mlflow-skinny`` has neither), a file store ``MLFLOW_ALLOW_FILE_STORE=true``."""
    uri, default = tracking_uri(params)
    named = f"{uri} (MLflow's default)" if default else uri
    scheme = urlparse(uri).scheme.split("+", 1)[0].lower()
    scheme = "file" if len(scheme) <= 1 else scheme  # a path (C: is a drive)
    if scheme in DATABASES:
        lacking = [m for m in ("sqlalchemy", "alembic") if missing(m, "mlflow", "mlflow")]
        if lacking:
            return (f"MLflow's store {named} needs {' and '.join(lacking)}, not installed: pip install "
                    "'distilkit[mlflow]' (or a file store: MLFLOW_TRACKING_URI=./mlruns with "
                    "MLFLOW_ALLOW_FILE_STORE=true)")
    elif scheme == "file" and os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").strip().lower() not in ("true", "1"):
        return (f"MLflow's file store {named} needs MLFLOW_ALLOW_FILE_STORE=true (MLflow 3 refuses a file store "
                "without it): export MLFLOW_ALLOW_FILE_STORE=true, or use a database store (tracking_uri: "
                "sqlite:///mlflow.db, with pip install 'distilkit[mlflow]')")
    return None


class TrackioParams(TrackerParams):
    project: str | None = Field(None, description="Trackio project (default: the recipe's name, a sweep's name for "
                                                  "its runs)")
    group: str | None = Field(None, description="run group (default: the sweep, else the recipe)")


HOOKS.declare("tensorboard", "distilkit.engine.train.tensorboard:TensorBoardHook", card=None,
              description="TensorBoard event files: training values and validation scores",
              paper="TensorBoard (torch.utils.tensorboard)", params=TensorBoardParams, check=tensorboard_missing,
              tracker=True)
HOOKS.declare("wandb", f"{_TRACKERS}.to_wandb:WandbTracker", card=None,
              description="Weights & Biases runs: config, training values, validation scores, summary, report files",
              paper="Weights & Biases (wandb)", params=WandbParams, check=wandb_missing, ready=login_problem,
              tracker=True)
HOOKS.declare("mlflow", f"{_TRACKERS}.to_mlflow:MlflowTracker", card=None,
              description="MLflow runs: parameters, training values, validation scores, final scores, report "
                          "artifacts; a sweep's runs nested under one parent",
              paper="MLflow (mlflow.MlflowClient)", params=MlflowParams, check=mlflow_missing, ready=store_problem,
              tracker=True)
HOOKS.declare("trackio", f"{_TRACKERS}.to_trackio:TrackioTracker", card=None,
              description="Trackio runs (local): config, training values, validation scores, final scores, report "
                          "artifacts", paper="Trackio (trackio)", params=TrackioParams, check=trackio_missing,
              tracker=True)

__all__ = ["DATABASES", "HOST", "MlflowParams", "TensorBoardParams", "TrackerParams", "TrackioParams", "WandbParams",
           "login_problem", "missing", "mlflow_missing", "mode", "settings_files", "store_problem",
           "tensorboard_missing", "trackio_missing", "tracking_uri", "wandb_missing"]
