"""The MLflow tracker (``trackers: [{mlflow: {tracking_uri: ..., experiment: ...}}]``; ``pip install
'distilkit[mlflow]'``: MLflow's client, ``mlflow-skinny``, with SQLAlchemy for a local SQLite store): one MLflow run
per stage run, through :class:`mlflow.MlflowClient` only (MLflow's active-run stack is left alone). The resolved
configuration as parameters (``a/b/c`` keys), the identity as ``distilkit.*`` tags, values as metrics at distilkit's
steps, the final scores as metrics at the last step, the report, its plots and the summary as artifacts.

A sweep's runs are nested (``mlflow.parentRunId``) under one parent run named after the sweep, found or created by
the first of them under a lock in the sweep's folder, so MLflow's table shows the sweep with every variant x seed
under it. A resumed stage continues its run (the run id kept in ``trackers.json``).

MLflow's own variables win over the recipe: ``MLFLOW_TRACKING_URI`` (default, MLflow's: ``sqlite:///mlflow.db`` in
the working folder), ``MLFLOW_EXPERIMENT_ID`` and ``MLFLOW_EXPERIMENT_NAME`` (default: the recipe's name, a sweep's
name for its runs); ``MLFLOW_RUN_ID`` is not used (each stage is a run of its own). A
hard kill after values were logged past the checkpoint logs those steps again (MLflow keeps both entries).
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path
from typing import Any

from pydantic import Field

from distilkit.engine.train.trackers.base import RunIdentity, Tracker, TrackerParams, flatten, missing, setting
from distilkit.registry import HOOKS

BATCH = 100  # parameters, tags or metrics per log_batch call (MLflow's limit for parameters)


class MlflowParams(TrackerParams):
    tracking_uri: str | None = Field(None, description="where runs are recorded (MLFLOW_TRACKING_URI; default "
                                                       "MLflow's: sqlite:///mlflow.db in the working folder)")
    experiment: str | None = Field(None, description="experiment name (MLFLOW_EXPERIMENT_NAME; default: the "
                                                     "recipe's name, a sweep's name for its runs)")
    tags: dict[str, str] = Field(default_factory=dict, description="tags of every run")


def experiment_id(client: Any, name: str) -> str:
    """The id of experiment ``name``, created if there is none (another process creating it first is fine)."""
    found = client.get_experiment_by_name(name)
    if found is not None:
        return str(found.experiment_id)
    try:
        return str(client.create_experiment(name))
    except Exception:  # noqa: BLE001  created meanwhile by another run of the sweep
        found = client.get_experiment_by_name(name)
        if found is None:
            raise
        return str(found.experiment_id)


def sweep_parent(client: Any, experiment: str, identity: RunIdentity) -> str:
    """The sweep's parent run in ``experiment``: found by its tags (the sweep and its folder), else created; under
    a lock in the sweep's folder so that the runs of a sweep started together make one."""
    from distilkit.engine.store.lock import stage_lock

    assert identity.sweep is not None
    root = str(identity.sweep_root.resolve())
    with stage_lock(identity.sweep_root / ".locks" / "mlflow-sweep.lock"):
        found = client.search_runs([experiment], max_results=1,
                                   filter_string=f"tags.`distilkit.role` = 'sweep' AND tags.`distilkit.sweep` = "
                                                 f"'{identity.sweep}' AND tags.`distilkit.sweep_root` = '{root}'")
        if found:
            return str(found[0].info.run_id)
        run = client.create_run(experiment, run_name=identity.sweep, tags={
            "distilkit.role": "sweep", "distilkit.sweep": identity.sweep, "distilkit.sweep_root": root,
            "distilkit.sweep_report": str((identity.sweep_root / "results.md").resolve())})
        return str(run.info.run_id)


class MlflowTracker(Tracker):
    key = "mlflow"

    def __init__(self, params: MlflowParams) -> None:
        super().__init__(params)
        self.params: MlflowParams = params
        self.client: Any = None
        self.run_id: str | None = None
        self.parent: str | None = None  # a sweep's parent run
        self.step = 0

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        from mlflow import MlflowClient

        p = self.params
        self.client = MlflowClient(tracking_uri=setting(p.tracking_uri, "MLFLOW_TRACKING_URI"))
        self.step = step
        if isinstance(resume, dict) and resume.get("run_id"):
            self.run_id = str(resume["run_id"])
            self.parent = resume.get("parent")
            self.client.update_run(self.run_id, status="RUNNING")
            return
        experiment = os.environ.get("MLFLOW_EXPERIMENT_ID") or experiment_id(
            self.client, os.environ.get("MLFLOW_EXPERIMENT_NAME") or p.experiment or identity.group)
        tags = {**identity.tags(), **p.tags}
        if identity.sweep is not None:
            self.parent = tags["mlflow.parentRunId"] = sweep_parent(self.client, experiment, identity)
        run = self.client.create_run(experiment, run_name=identity.name, tags=tags)
        self.run_id = str(run.info.run_id)
        self.keep({"run_id": self.run_id, "tracking_uri": self.client.tracking_uri, "parent": self.parent})
        self._batch(params={k: _text(v) for k, v in flatten(identity.full_config()).items()})

    def _batch(self, metrics: dict[str, float] | None = None, step: int = 0,
               params: dict[str, str] | None = None) -> None:
        from mlflow.entities import Metric, Param

        now = int(time.time() * 1000)
        items: list[Any] = [Param(_name(k), v) for k, v in (params or {}).items()]
        items += [Metric(k, v, now, step) for k, v in (metrics or {}).items()]
        for i in range(0, len(items), BATCH):
            chunk = items[i:i + BATCH]
            self.client.log_batch(self.run_id, metrics=[m for m in chunk if isinstance(m, Metric)],
                                  params=[m for m in chunk if isinstance(m, Param)])

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.step = step
        self._batch(values, step)

    def files(self, paths: list[Path]) -> None:
        for path in paths:
            self.client.log_artifact(self.run_id, str(path))

    def summary(self, values: dict[str, Any]) -> None:
        self._batch({k: float(v) for k, v in values.items() if isinstance(v, (int, float))}, self.step)
        for key, value in values.items():
            if not isinstance(value, (int, float)):
                self.client.set_tag(self.run_id, f"distilkit.{key}", str(value))

    def finish(self, finished: bool) -> None:
        if self.run_id is not None:
            self.client.set_terminated(self.run_id, "FINISHED" if finished else "KILLED")
            if finished and self.parent is not None:  # the sweep's parent ends with its latest run
                self.client.set_terminated(self.parent, "FINISHED")
            self.run_id = None


def _name(key: str) -> str:
    """A parameter's name as MLflow takes it: letters, digits, ``_-. :/`` (others become ``_``), 250 at most
    (``overrides/stages.*.train.steps`` -> ``overrides/stages._.train.steps``)."""
    return re.sub(r"[^A-Za-z0-9_\-. :/]", "_", key)[:250]


def _text(value: Any) -> str:
    """A parameter's value as MLflow keeps it (at most 6000 characters)."""
    return str(value)[:6000]


HOOKS.add("mlflow", MlflowTracker, description="MLflow runs: parameters, training values, validation scores, final "
                                               "scores, report artifacts; a sweep's runs nested under one parent",
          paper="MLflow (mlflow.MlflowClient)", params=MlflowParams,
          check=lambda: missing("mlflow", "mlflow", "mlflow"), tracker=True)

__all__ = ["MlflowParams", "MlflowTracker"]
