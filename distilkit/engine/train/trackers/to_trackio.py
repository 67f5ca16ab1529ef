"""The Trackio tracker (``trackers: [{trackio: {project: ...}}]``; ``pip install 'distilkit[trackio]'``): one Trackio
run per stage run in a local project (Trackio's SQLite files under ``TRACKIO_DIR``, default
``~/.cache/huggingface/trackio``; ``trackio show`` opens its dashboard), grouped by the sweep (or the recipe),
the resolved configuration and the identity as the run's config, values at distilkit's steps, the final scores
logged at the last step, the report and its plots as artifacts. Trackio's console output is kept out of
distilkit's.

Trackio's own variables win over the recipe: ``TRACKIO_DIR`` (read when Trackio is imported), and
``TRACKIO_SPACE_ID``/``TRACKIO_SERVER_URL`` (a Space or a server instead of the local files; distilkit passes
neither).

A resumed stage continues its own run: Trackio's run id, its project, name and folder are kept in
``trackers.json`` (a run's name, ``<stage>-<hash>``, is the same for the same recipe in another output folder, so
a name never says which run), and the resumed process logs to that id. Where ``TRACKIO_DIR`` is another folder
than the run's, the stage starts a new run there with a warning; either way the steps up to the checkpoint that the
run lacks are logged from ``metrics.jsonl`` (Trackio writes in the background: a killed process loses the values it
had queued). With a Space or a server, Trackio resumes by name only. Trackio has no run status: a stage that fails
is an ``error`` alert on its run, one stopped (SIGTERM, ``--stop-after``) a ``warn`` alert; both show in its
dashboard.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from distilkit.cards.trackers import TrackioParams
from distilkit.engine.train.trackers.base import RunIdentity, Tracker, quiet

REMOTE = ("TRACKIO_SPACE_ID", "TRACKIO_SERVER_URL")


class TrackioTracker(Tracker):
    key = "trackio"

    def __init__(self, params: TrackioParams) -> None:
        super().__init__(params)
        self.params: TrackioParams = params
        self.run: Any = None
        self.step = 0

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        import trackio
        import trackio.utils

        p = self.params
        here = str(Path(trackio.utils.TRACKIO_DIR).resolve())
        remote = any(os.environ.get(v) for v in REMOTE)
        kept = resume if isinstance(resume, dict) and resume.get("id") else None
        if kept is not None and not remote and kept.get("dir") != here:
            self.warn(f"Trackio's folder is {here}, the stage's Trackio run {kept.get('name')} ({kept['id']}) is in "
                      f"{kept.get('dir')}: a new run is started here, with every value the stage kept")
            kept = None
        self.step = step
        settings = dict(group=p.group or identity.group, config=identity.full_config(), auto_log_gpu=False,
                        auto_log_cpu=False)
        with quiet():
            if kept is not None and not remote:  # its own run, by id
                self.run = trackio.Run(url=None, project=kept["project"], client=None, name=kept["name"],
                                       run_id=kept["id"], **settings)
                return
            if kept is not None:
                self.run = trackio.init(project=kept["project"], name=kept["name"], resume="allow", embed=False,
                                        **settings)
            else:
                self.run = trackio.init(project=p.project or identity.group, name=identity.name, resume="never",
                                        embed=False, **settings)
        self.keep({"project": self.run.project, "name": self.run.name, "id": self.run.id,
                   "dir": next((f"{v}={os.environ[v]}" for v in REMOTE if os.environ.get(v)), here)})

    def held(self, step: int) -> int:
        if any(os.environ.get(v) for v in REMOTE):
            return step
        from trackio.sqlite_storage import SQLiteStorage

        with quiet():
            last = SQLiteStorage.get_max_step_for_run(self.run.project, self.run.name, run_id=self.run.id)
        return int(last or 0)

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.step = step
        with quiet():
            self.run.log(values, step=step)

    def files(self, paths: list[Path]) -> None:
        with quiet():
            for path in paths:
                self.run.log_artifact(str(path), name=f"{self.run.name}-{path.name}".replace("/", "-"), type="report")

    def summary(self, values: dict[str, Any]) -> None:
        with quiet():
            self.run.log({k: float(v) for k, v in values.items() if isinstance(v, (int, float))}, step=self.step)

    def finish(self, status: str, why: str = "") -> None:
        if self.run is None:
            return
        import trackio.context_vars
        from trackio.alerts import AlertLevel

        run, self.run = self.run, None
        with quiet():
            if status != "finished":
                run.alert(f"stage {status}", text=why or None,
                          level=AlertLevel.ERROR if status == "failed" else AlertLevel.WARN)
            run.finish()
        if trackio.context_vars.current_run.get() is run:  # finished: not again when the process exits (a print)
            trackio.context_vars.current_run.set(None)


__all__ = ["TrackioParams", "TrackioTracker"]
