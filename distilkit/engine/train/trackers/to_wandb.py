"""The Weights & Biases tracker (``trackers: [{wandb: {project: ..., mode: offline}}]``; ``pip install
'distilkit[wandb]'``): one W&B run per stage run, its resolved configuration as the run's config, grouped by the
sweep (or the recipe), the variant as its job type; values logged at distilkit's steps (``step=``), the final scores
as the run's summary, the report and its plots as the run's files.

W&B's own variables win over the recipe: ``WANDB_MODE``, ``WANDB_PROJECT``, ``WANDB_ENTITY``, ``WANDB_DIR``,
``WANDB_RUN_GROUP`` (a setting whose variable is set is not passed); ``WANDB_RUN_ID`` is not used (each stage is
a run of its own, with the id kept in its folder). ``mode: offline`` writes ``<dir>/wandb/offline-run-*`` (default
dir: the stage's run folder) and needs no login; ``wandb sync`` uploads it. ``mode: disabled`` (or
``WANDB_MODE=disabled``, or ``mode = disabled`` in wandb's settings) logs nothing: W&B is not even started. An
online run needs a login, which ``validate`` looks for (``WANDB_API_KEY``, a netrc entry for the host, wandb's
settings) without the network.

A stage that fails ends its run with exit code 1 (W&B: failed); one stopped (SIGTERM, ``--stop-after``) is marked
preempting and ends with exit code 1 (W&B: preempted, resumable).

A resumed stage continues its run (the id kept in ``trackers.json``, ``resume="allow"``); offline, each process
writes a folder of its own with that one id, which ``wandb sync`` joins in order. W&B's service writes an offline
run's records when it ends, so a process killed outright (SIGKILL, out of memory) leaves a file with none of the
steps it logged (or only those of the 32 KiB blocks it filled): the resumed process reads the run's earlier
folders (:func:`logged_step`) and logs again, from ``metrics.jsonl``, every step up to its checkpoint that they
lack, and no step they have. Together the folders hold each step once, with the values the run kept.
"""

from __future__ import annotations

import secrets
import struct
from pathlib import Path
from typing import Any, Iterator

from distilkit.cards.trackers import HOST, WandbParams, login_problem, mode, settings_files
from distilkit.engine.train.trackers.base import RunIdentity, Tracker, setting

BLOCK = 32768  # the offline file's block (LevelDB's log format, with W&B's 7-byte header)


def records(path: Path) -> Iterator[Any]:
    """The complete records of a W&B run file (``run-<id>.wandb``): a ``:W&B`` header, then records in 32 KiB
    blocks, each chunk with a 7-byte header (checksum, length, type: full, first, middle, last); a record cut by a
    kill is left out."""
    from wandb.proto import wandb_internal_pb2 as pb

    data = path.read_bytes()
    if data[:4] != b":W&B":
        return
    pos, parts = 7, []
    while pos + 7 <= len(data):
        left = BLOCK - pos % BLOCK
        if left < 7:
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        if length == 0 and kind == 0:  # the rest of the block
            pos += left
            continue
        if pos + 7 + length > len(data):
            return
        parts.append(data[pos + 7:pos + 7 + length])
        pos += 7 + length
        if kind in (1, 4):  # full, last
            record = pb.Record()
            record.ParseFromString(b"".join(parts))
            parts = []
            yield record


def logged_step(wandb_dir: Path, run_id: str, this: Path) -> int:
    """The last history step the run's other folders in ``wandb_dir`` (``*-<id>``, not ``this`` process's) hold."""
    last = 0
    for path in wandb_dir.glob(f"*-{run_id}/run-{run_id}.wandb"):
        if path.parent.resolve() == this.resolve():
            continue
        for record in records(path):
            if record.WhichOneof("record_type") == "history":
                last = max(last, int(record.history.step.num))
    return last


class WandbTracker(Tracker):
    key = "wandb"

    def __init__(self, params: WandbParams) -> None:
        super().__init__(params)
        self.params: WandbParams = params
        self.run: Any = None

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        p = self.params
        if mode(p) == "disabled":  # nothing logged, nothing kept
            return
        import wandb

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
        if self.run.disabled:  # disabled where distilkit does not look (a settings file of its own): nothing
            self.run.finish()
            self.run = None

    def held(self, step: int) -> int:
        if self.run is None:
            return step
        folder = Path(self.run.dir).parent  # <dir>/wandb/<this process's folder>/files
        return logged_step(folder.parent, self.run.id, folder)

    def scalars(self, values: dict[str, float], step: int) -> None:
        if self.run is not None:
            self.run.log(values, step=step)

    def files(self, paths: list[Path]) -> None:
        """Copied into the run's files folder, which W&B uploads when the run ends (``wandb sync`` offline)."""
        import shutil

        if self.run is None:
            return
        for path in paths:
            shutil.copy2(path, Path(self.run.dir) / path.name)

    def summary(self, values: dict[str, Any]) -> None:
        if self.run is not None:
            self.run.summary.update(values)

    def finish(self, status: str, why: str = "") -> None:
        if self.run is None:
            return
        run, self.run = self.run, None
        if status == "stopped":  # resumable: W&B shows it preempted (a sweep requeues it)
            run.mark_preempting()
        run.finish(exit_code=0 if status == "finished" else 1)


__all__ = ["HOST", "WandbParams", "WandbTracker", "logged_step", "login_problem", "mode", "records", "settings_files"]
