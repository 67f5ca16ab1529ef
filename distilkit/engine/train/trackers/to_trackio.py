"""The Trackio tracker (``trackers: [{trackio: {project: ...}}]``; ``pip install 'distilkit[trackio]'``): one Trackio
run per stage run in a local project (Trackio's SQLite files under ``TRACKIO_DIR``, default
``~/.cache/huggingface/trackio``; ``trackio show`` opens its dashboard), grouped by the sweep (or the recipe),
the resolved configuration and the identity as the run's config, values at distilkit's steps, the final scores
logged at the last step, the report and its plots as artifacts.

Trackio's own variables win over the recipe: ``TRACKIO_DIR`` (read when Trackio is imported), and
``TRACKIO_SPACE_ID``/``TRACKIO_SERVER_URL`` (a Space or a server instead of the local files; distilkit passes
neither). A resumed stage continues its run by name (kept in ``trackers.json``, ``resume="must"``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import Field

from distilkit.engine.train.trackers.base import RunIdentity, Tracker, TrackerParams, missing
from distilkit.registry import HOOKS


class TrackioParams(TrackerParams):
    project: str | None = Field(None, description="Trackio project (default: the recipe's name, a sweep's name for "
                                                  "its runs)")
    group: str | None = Field(None, description="run group (default: the sweep, else the recipe)")


class TrackioTracker(Tracker):
    key = "trackio"

    def __init__(self, params: TrackioParams) -> None:
        super().__init__(params)
        self.params: TrackioParams = params
        self.run: Any = None
        self.step = 0

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        import trackio

        p = self.params
        kept = resume if isinstance(resume, dict) and resume.get("name") else None
        project = kept["project"] if kept else p.project or identity.group
        name = kept["name"] if kept else identity.name
        self.keep({"project": project, "name": name})
        self.step = step
        self.run = trackio.init(project=project, name=name, group=p.group or identity.group,
                                config=identity.full_config(), resume="must" if kept else "never", embed=False,
                                auto_log_gpu=False, auto_log_cpu=False)

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.step = step
        self.run.log(values, step=step)

    def files(self, paths: list[Path]) -> None:
        for path in paths:
            self.run.log_artifact(str(path), name=f"{self.run.name}-{path.name}".replace("/", "-"), type="report")

    def summary(self, values: dict[str, Any]) -> None:
        self.run.log({k: float(v) for k, v in values.items() if isinstance(v, (int, float))}, step=self.step)

    def finish(self, finished: bool) -> None:
        if self.run is not None:
            self.run.finish()
            self.run = None


HOOKS.add("trackio", TrackioTracker, description="Trackio runs (local): config, training values, validation scores, "
                                                 "final scores, report artifacts", paper="Trackio (trackio)",
          params=TrackioParams, check=lambda: missing("trackio", "trackio", "trackio"), tracker=True)

__all__ = ["TrackioParams", "TrackioTracker"]
