"""The training loop's lifecycle hooks (as in Pointcept): after every step, in this order, logging,
progress, evaluation on the validation split (choosing ``best.pt``) and checkpointing (``last.pt``).
The loop itself (:meth:`Trainer.fit`) only draws batches and takes optimizer steps."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from distilkit.engine.trainer import Trainer


@dataclass
class LoopState:
    """What the hooks share: the step just finished, its logged values, the best and latest scores."""

    step: int
    total: int
    best: dict[str, Any]
    values: dict[str, float] = field(default_factory=dict)
    last_scores: dict[str, Any] | None = None
    evaluated: bool = False  # an evaluation ran at this step
    t0: float = field(default_factory=time.perf_counter)


class Hook:
    def after_step(self, trainer: "Trainer", state: LoopState) -> None:
        """Called after every optimizer step (``state.step`` counts finished steps)."""


class LogHook(Hook):
    """Training values to ``metrics.jsonl`` every ``log_every`` steps and at the last step."""

    def after_step(self, trainer: "Trainer", state: LoopState) -> None:
        spec = trainer.stage.spec.train
        if state.step % spec.log_every == 0 or state.step == state.total:
            trainer._log({"step": state.step, "epoch": (state.step - 1) // trainer.steps_per_epoch, **state.values,
                          "lr": trainer.optimizer.param_groups[0]["lr"], "time": time.perf_counter() - state.t0})


class ProgressHook(Hook):
    """The caller's progress callback (a progress bar): step, total, values."""

    def __init__(self, on_step: Callable[[int, int, dict[str, float]], None]) -> None:
        self.on_step = on_step

    def after_step(self, trainer: "Trainer", state: LoopState) -> None:
        self.on_step(state.step, state.total, state.values)


class EvalHook(Hook):
    """Validation every ``eval_every`` steps and at the end; a better score writes ``best.pt``."""

    def after_step(self, trainer: "Trainer", state: LoopState) -> None:
        state.evaluated = state.step % trainer.eval_every == 0 or state.step == state.total
        if not state.evaluated:
            return
        scores = trainer.evaluate(trainer.val_set)
        state.last_scores = scores
        trainer._log({"step": state.step, "eval": scores})
        score, metric = scores[trainer.metric.key], trainer.metric
        best = state.best
        if best["scores"] is None or (score > best["score"] if metric.higher_is_better else score < best["score"]):
            state.best = {"score": score, "step": state.step, "scores": scores}
            trainer._save_best(state.step, scores)


class CheckpointHook(Hook):
    """``last.pt`` at every evaluation and every ``checkpoint_every`` steps (model, optimizers, RNG, best)."""

    def after_step(self, trainer: "Trainer", state: LoopState) -> None:
        if state.evaluated or state.step % trainer.stage.spec.train.checkpoint_every == 0:
            trainer._save_last(state.step, state.best)
