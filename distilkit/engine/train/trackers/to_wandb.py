"""The Weights & Biases tracker (``trackers: [{wandb: {project: ..., mode: offline}}]``; ``pip install
'distilkit[wandb]'``): one W&B run per stage run, its resolved configuration as the run's config, grouped by the
sweep (or the recipe), the variant as its job type; values logged at distilkit's steps (``step=``), the final scores
as the run's summary, the report and its plots as the run's files.

W&B's own variables win over the recipe: ``WANDB_MODE``, ``WANDB_PROJECT``, ``WANDB_ENTITY``, ``WANDB_DIR``,
``WANDB_RUN_GROUP`` (a setting whose variable is set is not passed); ``WANDB_RUN_ID`` is not used (each stage is
a run of its own, with the id kept in its folder). ``mode: offline`` writes
``<dir>/wandb/offline-run-*`` (default dir: the stage's run folder) and needs no login; ``wandb sync`` uploads it.
A resumed stage continues its run (the id kept in ``trackers.json``, ``resume="allow"``): offline, each process
writes a folder of its own with that one id, which ``wandb sync`` joins. W&B drops values at a step below one it
already has, so after a hard kill (no ``last.pt`` at the last logged step) the steps logged twice keep their
first values (a deterministic run logs the same ones again).
"""

from __future__ import annotations

import secrets
from pathlib import Path
from typing import Any, Literal

from pydantic import Field

from distilkit.engine.train.trackers.base import RunIdentity, Tracker, TrackerParams, missing, setting
from distilkit.registry import HOOKS


class WandbParams(TrackerParams):
    project: str | None = Field(None, description="W&B project (WANDB_PROJECT; default: the recipe's name, a "
                                                  "sweep's name for its runs)")
    entity: str | None = Field(None, description="W&B entity, a user or team (WANDB_ENTITY; default: W&B's)")
    mode: Literal["online", "offline", "disabled"] | None = Field(None, description="WANDB_MODE; default W&B's "
                                                                                    "(online)")
    dir: str | None = Field(None, description="where W&B writes its files (WANDB_DIR; default: the stage's run "
                                              "folder)")
    group: str | None = Field(None, description="run group (WANDB_RUN_GROUP; default: the sweep, else the recipe)")
    tags: list[str] = Field(default_factory=list, description="tags of every run")


class WandbTracker(Tracker):
    key = "wandb"

    def __init__(self, params: WandbParams) -> None:
        super().__init__(params)
        self.params: WandbParams = params
        self.run: Any = None

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        import wandb

        p = self.params
        run_id = resume if isinstance(resume, str) and resume else secrets.token_hex(6)  # W&B's id rules: [a-z0-9]
        self.keep(run_id)  # before the run exists: a kill during init still resumes this id
        tags = [*p.tags, *([identity.sweep] if identity.sweep else []), identity.variant or identity.stage]
        self.run = wandb.init(
            id=run_id, resume="allow", reinit="create_new",
            project=setting(p.project, "WANDB_PROJECT", identity.recipe), entity=setting(p.entity, "WANDB_ENTITY"),
            mode=setting(p.mode, "WANDB_MODE"), dir=setting(p.dir, "WANDB_DIR", str(identity.run_dir)),
            group=setting(p.group, "WANDB_RUN_GROUP", identity.group), job_type=identity.variant or identity.stage,
            name=identity.name, config=identity.full_config(), tags=list(dict.fromkeys(tags)),
            settings=wandb.Settings(console="off", silent=True))

    def scalars(self, values: dict[str, float], step: int) -> None:
        self.run.log(values, step=step)

    def files(self, paths: list[Path]) -> None:
        """Copied into the run's files folder, which W&B uploads when the run ends (``wandb sync`` offline)."""
        import shutil

        for path in paths:
            shutil.copy2(path, Path(self.run.dir) / path.name)

    def summary(self, values: dict[str, Any]) -> None:
        self.run.summary.update(values)

    def finish(self, finished: bool) -> None:
        if self.run is None:
            return
        if not finished:
            self.run.mark_preempting()
        self.run.finish()
        self.run = None


HOOKS.add("wandb", WandbTracker, description="Weights & Biases runs: config, training values, validation scores, "
                                             "summary, report files", paper="Weights & Biases (wandb)",
          params=WandbParams, check=lambda: missing("wandb", "wandb", "wandb"), tracker=True)

__all__ = ["WandbParams", "WandbTracker"]
