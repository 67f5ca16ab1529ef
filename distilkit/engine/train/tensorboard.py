"""The TensorBoard logger, a registered lifecycle hook (``train.hooks: [{name: tensorboard}]``), as the field's
trainers offer beside their own logs: every logged training value (each weighted term, the total loss, the learning
rate) and every scalar validation score, by step, into ``<run>/tensorboard/``. Needs the optional extra
(``pip install "distilkit[tensorboard]"``); ``validate`` says so when it is missing. ``metrics.jsonl`` stays the
record the reports read."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from distilkit.engine.hooks import Hook, Loop
from distilkit.registry import HOOKS


class TensorBoardParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    every: int = Field(0, ge=0, description="write training values every N steps (0: as often as log_every)")
    folder: str = Field("tensorboard", min_length=1, description="the event files' folder inside the run folder")


def available() -> str | None:
    """None when the writer can be made, else what to install."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError as exc:
        return f"the tensorboard hook needs the tensorboard package ({exc}); pip install \"distilkit[tensorboard]\""
    return None


class TensorBoardHook(Hook):
    def __init__(self, params: TensorBoardParams) -> None:
        self.params = params
        self.writer: Any = None

    def before_train(self, loop: Loop) -> None:
        if loop.main:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(loop.run_dir / self.params.folder), purge_step=loop.step + 1)

    def after_step(self, loop: Loop) -> None:
        every = self.params.every or loop.spec.log_every
        if self.writer is None or not (loop.step % every == 0 or loop.step == loop.total):
            return
        for key, value in loop.values.items():
            self.writer.add_scalar(f"train/{key}", float(value), loop.step)

    def after_evaluation(self, loop: Loop, scores: dict[str, Any]) -> None:
        if self.writer is None:
            return
        for key, value in scores.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                self.writer.add_scalar(f"val/{key}", float(value), loop.step)

    def after_train(self, loop: Loop) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


HOOKS.add("tensorboard", TensorBoardHook, description="TensorBoard event files: training values and validation scores",
          paper="TensorBoard (torch.utils.tensorboard)", params=TensorBoardParams, check=available)

__all__ = ["TensorBoardHook", "TensorBoardParams"]
