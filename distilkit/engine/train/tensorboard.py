"""The TensorBoard logger, a tracker (``trackers: [tensorboard]``, or as a lifecycle hook of one stage,
``train.hooks: [{name: tensorboard}]``), as the field's trainers offer beside their own logs: every logged training
value (each weighted term, the total loss, the learning rate) and every scalar validation score, by step, into
``<run>/tensorboard/`` (:class:`~distilkit.engine.train.trackers.base.Tracker` chooses the values and steps, the
same for every tracker). Needs the optional extra (``pip install "distilkit[tensorboard]"``); ``validate`` says so
when it is missing. ``metrics.jsonl`` stays the record the reports read."""

from __future__ import annotations

from typing import Any

from pydantic import Field

from distilkit.engine.hooks import Loop
from distilkit.engine.train.trackers.base import RunIdentity, Tracker, TrackerParams
from distilkit.registry import HOOKS


class TensorBoardParams(TrackerParams):
    folder: str = Field("tensorboard", min_length=1, description="the event files' folder inside the run folder")


def available() -> str | None:
    """None when the writer can be made, else what to install."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError as exc:
        return f"the tensorboard hook needs the tensorboard package ({exc}); pip install \"distilkit[tensorboard]\""
    return None


class TensorBoardHook(Tracker):
    key = "tensorboard"

    def __init__(self, params: TensorBoardParams) -> None:
        super().__init__(params)
        self.params: TensorBoardParams = params
        self.writer: Any = None

    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        from torch.utils.tensorboard import SummaryWriter

        # a resumed run drops the events a killed process wrote after its checkpoint
        self.writer = SummaryWriter(str(identity.run_dir / self.params.folder), purge_step=step + 1)

    def scalars(self, values: dict[str, float], step: int) -> None:
        for key, value in values.items():
            self.writer.add_scalar(key, value, step)

    def finish(self, finished: bool) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def after_train(self, loop: Loop) -> None:
        """The event files are closed when the loop ends (the report reads ``metrics.jsonl``, not them)."""
        if self.active:
            self.active = False
            self.finish(loop.step == loop.total)


HOOKS.add("tensorboard", TensorBoardHook, description="TensorBoard event files: training values and validation scores",
          paper="TensorBoard (torch.utils.tensorboard)", params=TensorBoardParams, check=available, tracker=True)

__all__ = ["TensorBoardHook", "TensorBoardParams"]
