"""The MLflow tracker (``trackers: [{mlflow: {tracking_uri: ..., experiment: ...}}]``; ``pip install
'distilkit[mlflow]'``: MLflow's client, ``mlflow-skinny``, with SQLAlchemy and Alembic for a database store such as
MLflow's default ``sqlite:///mlflow.db``): one MLflow run per stage run, through :class:`mlflow.MlflowClient` only
(MLflow's active-run stack is left alone). The resolved configuration as parameters (``a/b/c`` keys), the identity
as ``distilkit.*`` tags, values as metrics at distilkit's steps, the final scores as metrics at the last step, the
report, its plots and the summary as artifacts. A stage that fails ends its run ``FAILED`` (the error in the tag
``distilkit.ended``), one stopped (SIGTERM, ``--stop-after``) ``KILLED``; a finished one ``FINISHED``.

A sweep's runs are nested (``mlflow.parentRunId``) under one parent run named after the sweep, found or created by
the first of them under a lock in the sweep's folder, so MLflow's table shows the sweep with every variant x seed
under it.

MLflow's own variables win over the recipe: ``MLFLOW_TRACKING_URI`` (default, MLflow's: ``sqlite:///mlflow.db`` in
the working folder, or ``./mlruns`` where that holds runs), ``MLFLOW_EXPERIMENT_ID`` and ``MLFLOW_EXPERIMENT_NAME``
(default: the recipe's name, a sweep's name for its runs); ``MLFLOW_RUN_ID`` is not used (each stage is a run of
its own). A file store needs ``MLFLOW_ALLOW_FILE_STORE=true`` (MLflow 3 refuses it otherwise): ``validate`` checks
what the store needs.

A resumed stage continues its run in the store it was recorded in: the run id and the tracking URI (made absolute)
are kept in ``trackers.json``, so a resume from another working folder, or with another ``MLFLOW_TRACKING_URI``,
still finds it; a run no longer there is one warning and a new run in the current store. Each step's values go in
one ``log_batch`` with the tag ``distilkit.logged_step``, read back on a resume: the steps up to the checkpoint the
run lacks are logged from ``metrics.jsonl``, none twice.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path
from typing import Any

from distilkit.cards.trackers import DATABASES, MlflowParams, store_problem, tracking_uri
from distilkit.engine.train.trackers.base import RunIdentity, Tracker, flatten, one_line, quiet, setting

BATCH = 100  # parameters per log_batch call (MLflow's limit)
METRICS_BATCH = 900  # metrics per log_batch call (MLflow's limit: 1000 metrics, 1000 entities in all)
LOGGED = "distilkit.logged_step"  # the run's tag: the last step whose values were logged (in the same batch)
STATUS = {"finished": "FINISHED", "stopped": "KILLED", "failed": "FAILED"}
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


def absolute_uri(uri: str) -> str:
    """A local store's URI made absolute (``sqlite:///mlflow.db``, ``mlruns``: relative to the working folder),
    so that a resume from another folder finds the same store; others as they are."""
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////") and ":memory:" not in uri:
        return "sqlite:///" + str(Path(uri[len("sqlite:///"):]).resolve())
    if "://" not in uri and not uri.startswith("file:"):
        return Path(uri).resolve().as_uri()
    return uri


class MlflowTracker(Tracker):
    key = "mlflow"

    def __init__(self, params: MlflowParams) -> None:
        super().__init__(params)
        self.params: MlflowParams = params
        self.client: Any = None
        self.run_id: str | None = None
        self.parent: str | None = None  # a sweep's parent run
        self.step = 0
        self.logged = 0  # the run's last step logged (its tag), read on a resume

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        self.step = step
        if isinstance(resume, dict) and resume.get("run_id"):
            with quiet():
                gone = self._continue(resume)
            if gone is None:
                return
            self.warn(gone)
        with quiet():
            self._create(identity)

    def _continue(self, kept: dict[str, Any]) -> str | None:
        """Continue the run kept in ``trackers.json``, in its store; where it is not there, what to warn of."""
        from mlflow import MlflowClient

        uri = kept.get("tracking_uri") or setting(self.params.tracking_uri, "MLFLOW_TRACKING_URI")
        try:
            self.client = MlflowClient(tracking_uri=uri)
            run = self.client.get_run(str(kept["run_id"]))
        except Exception as exc:  # noqa: BLE001  not there (another store, deleted): a new run
            return (f"MLflow run {kept['run_id']} (kept in trackers.json) is not in {uri} ({one_line(exc)}); a new "
                    "run is started in the current store, with every value the stage kept")
        self.run_id, self.parent = str(kept["run_id"]), kept.get("parent")
        self.logged = int(run.data.tags.get(LOGGED, 0) or 0)
        self.client.update_run(self.run_id, status="RUNNING")
        return None

    def _create(self, identity: RunIdentity) -> None:
        from mlflow import MlflowClient

        p = self.params
        self.client = MlflowClient(tracking_uri=setting(p.tracking_uri, "MLFLOW_TRACKING_URI"))
        self.logged = 0
        experiment = os.environ.get("MLFLOW_EXPERIMENT_ID") or experiment_id(
            self.client, os.environ.get("MLFLOW_EXPERIMENT_NAME") or p.experiment or identity.group)
        tags = {**identity.tags(), **p.tags}
        if identity.sweep is not None:
            self.parent = tags["mlflow.parentRunId"] = sweep_parent(self.client, experiment, identity)
        run = self.client.create_run(experiment, run_name=identity.name, tags=tags)
        self.run_id = str(run.info.run_id)
        self.keep({"run_id": self.run_id, "tracking_uri": absolute_uri(self.client.tracking_uri),
                   "parent": self.parent})
        self._params({k: _text(v) for k, v in flatten(identity.full_config()).items()})

    def held(self, step: int) -> int:
        return self.logged

    def _params(self, params: dict[str, str]) -> None:
        from mlflow.entities import Param

        items = [Param(_name(k), v) for k, v in params.items()]
        for i in range(0, len(items), BATCH):
            self.client.log_batch(self.run_id, params=items[i:i + BATCH])

    def _metrics(self, metrics: dict[str, float], step: int, mark: bool) -> None:
        """The step's metrics; ``mark``: with the tag that says the step is logged, in the last batch."""
        from mlflow.entities import Metric, RunTag

        now = int(time.time() * 1000)
        items = [Metric(k, v, now, step) for k, v in metrics.items()]
        chunks = [items[i:i + METRICS_BATCH] for i in range(0, len(items), METRICS_BATCH)] or [[]]
        with quiet():
            for n, chunk in enumerate(chunks, 1):
                tags = [RunTag(LOGGED, str(step))] if mark and n == len(chunks) else []
                self.client.log_batch(self.run_id, metrics=chunk, tags=tags)

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.step = step
        self._metrics(values, step, mark=True)

    def files(self, paths: list[Path]) -> None:
        with quiet():
            for path in paths:
                self.client.log_artifact(self.run_id, str(path))

    def summary(self, values: dict[str, Any]) -> None:
        self._metrics({k: float(v) for k, v in values.items() if isinstance(v, (int, float))}, self.step, mark=False)
        with quiet():
            for key, value in values.items():
                if not isinstance(value, (int, float)):
                    self.client.set_tag(self.run_id, f"distilkit.{key}", str(value))

    def finish(self, status: str, why: str = "") -> None:
        if self.run_id is None:
            return
        with quiet():
            if why:
                self.client.set_tag(self.run_id, "distilkit.ended", why[:5000])
            self.client.set_terminated(self.run_id, STATUS[status])
            if status == "finished" and self.parent is not None:  # the sweep's parent ends with its latest run
                self.client.set_terminated(self.parent, "FINISHED")
        self.run_id = None


def _name(key: str) -> str:
    """A parameter's name as MLflow takes it: letters, digits, ``_-. :/`` (others become ``_``), 250 at most
    (``overrides/stages.*.train.steps`` -> ``overrides/stages._.train.steps``)."""
    return re.sub(r"[^A-Za-z0-9_\-. :/]", "_", key)[:250]


def _text(value: Any) -> str:
    """A parameter's value as MLflow keeps it (at most 6000 characters)."""
    return str(value)[:6000]


__all__ = ["DATABASES", "MlflowParams", "MlflowTracker", "absolute_uri", "store_problem", "tracking_uri"]
