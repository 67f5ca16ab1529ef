"""The TensorBoard logger, a tracker (``trackers: [tensorboard]``, or as a lifecycle hook of one stage,
``train.hooks: [{name: tensorboard}]``), as the field's trainers offer beside their own logs: every logged training
value (each weighted term, the total loss, the learning rate) and every scalar validation score, by step, into
``<run>/tensorboard/`` (:class:`~distilkit.engine.train.trackers.base.Tracker` chooses the values and steps, the
same for every tracker). Needs the optional extra (``pip install "distilkit[tensorboard]"``); ``validate`` says so
when it is missing. ``metrics.jsonl`` stays the record the reports read.

The writer is flushed each time values are handed to it (once a checkpoint covers them) and the last step flushed
is kept in ``trackers.json``; a resumed stage opens the writer with ``purge_step`` one past it, so TensorBoard drops
whatever a killed process wrote after that, and the steps from there to the checkpoint are written again from
``metrics.jsonl``: each step once."""

from __future__ import annotations

from typing import Any

from distilkit.cards.trackers import TensorBoardParams
from distilkit.cards.trackers import tensorboard_missing as available
from distilkit.engine.hooks import Loop
from distilkit.engine.train.trackers.base import RunIdentity, Tracker


class TensorBoardHook(Tracker):
    key = "tensorboard"

    def __init__(self, params: TensorBoardParams) -> None:
        super().__init__(params)
        self.params: TensorBoardParams = params
        self.writer: Any = None
        self.logged = 0  # the last step flushed to the event files

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.logged = int(resume.get("logged", 0)) if isinstance(resume, dict) else 0
        self.writer = SummaryWriter(str(identity.run_dir / self.params.folder), purge_step=self.logged + 1)

    def held(self, step: int) -> int:
        return self.logged

    def scalars(self, values: dict[str, float], step: int) -> None:
        for key, value in values.items():
            self.writer.add_scalar(key, value, step)

    def flush(self, step: int) -> None:
        self.writer.flush()
        self.logged = step
        self.keep({"logged": step})

    def finish(self, status: str, why: str = "") -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def after_train(self, loop: Loop) -> None:
        """The event files are closed when the loop ends (the report reads ``metrics.jsonl``, not them)."""
        super().after_train(loop)
        self.end("finished")


__all__ = ["TensorBoardHook", "TensorBoardParams", "available"]
