"""The training loop's lifecycle hooks (as in Pointcept and mmengine) and the public view of the loop they get.

A hook may implement any of ``before_train``, ``before_step``, ``after_step``, ``after_evaluation``,
``after_train``, ``after_publish`` and ``after_abort``; each receives the :class:`Loop` (never the trainer's
internals). The stage's own hooks run first, in this order, after every step: logging, progress, evaluation on the
validation split (choosing ``best.pt``) and checkpointing (``last.pt``); then the recipe's registered hooks
(``train.hooks``, e.g. ``tensorboard``) and its trackers (``trackers``: ``distilkit.engine.train.trackers``).
Plugins register hooks in ``HOOKS`` like any component: ``HOOKS.add(name, factory(params, loop_info), params=...)``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable



@dataclass
class Loop:
    """The loop as hooks see it: where it is, what the last step logged, the scores, and what a hook may ask of it
    (:meth:`log`, :meth:`evaluate`, :meth:`save`)."""

    stage: str
    run_dir: Path
    spec: Any  # the stage's train spec (log_every, eval_every, ...)
    total: int  # steps of the whole run
    steps_per_epoch: int
    eval_every: int
    main: bool  # the process that writes
    step: int = 0  # finished steps
    best: dict[str, Any] = field(default_factory=lambda: {"score": -1.0, "step": -1, "scores": None})
    values: dict[str, float] = field(default_factory=dict)  # what the last step logged (loss terms, lr, ...)
    last_scores: dict[str, Any] | None = None
    evaluated: bool = False  # an evaluation ran at this step
    saved: int = 0  # the step of the last ``last.pt`` written or resumed from (0: none)
    per_class: dict[str, list[str]] = field(default_factory=dict)  # a per-class score's key -> its entries' classes
    t0: float = field(default_factory=time.perf_counter)
    seconds: float = 0.0  # the loop's time, once it has ended
    waited: float = 0.0  # of it, the time spent waiting for the loader's next batch (this process's steps)
    # what the stage's run provides
    _log: Callable[[dict[str, Any]], None] = lambda record: None
    _evaluate: Callable[[], dict[str, Any]] = lambda: {}
    _save: Callable[[str], None] = lambda which: None
    _warn: Callable[[str], None] = lambda text: print(f"warning: {text}", file=sys.stderr)
    hooks: list["Hook"] = field(default_factory=list)

    @property
    def epoch(self) -> int:
        return max(self.step - 1, 0) // self.steps_per_epoch

    def log(self, record: dict[str, Any]) -> None:
        """A record for ``metrics.jsonl`` (written by the main process only)."""
        self._log(record)

    def evaluate(self) -> dict[str, Any]:
        """Scores of the current student on the validation split; every hook's ``after_evaluation`` sees them."""
        scores = self._evaluate()
        self.last_scores = scores
        for hook in self.hooks:
            hook.after_evaluation(self, scores)
        return scores

    def save(self, which: str) -> None:
        """Write ``last.pt`` (everything to resume from) or ``best.pt`` (the student and its scores)."""
        self._save(which)
        if which == "last":
            self.saved = self.step

    def warn(self, text: str) -> None:
        """One line for the user (on the stage's console, and in ``metrics.jsonl``): something went wrong that does
        not stop the stage (a tracker that failed)."""
        self._warn(text)

    def published(self, summary: dict[str, Any]) -> None:
        """Every hook's ``after_publish``: the finished stage's ``summary.json`` and report are written (a hook
        written before this moment existed, without the method, is passed over)."""
        for hook in self.hooks:
            after = getattr(hook, "after_publish", None)
            if after is not None:
                after(self, summary)

    def aborted(self, error: BaseException) -> None:
        """Every hook's ``after_abort``: the stage ends without publishing (a hook written before this moment
        existed, without the method, is passed over)."""
        for hook in self.hooks:
            after = getattr(hook, "after_abort", None)
            if after is not None:
                after(self, error)

    def emit(self, event: str) -> None:
        """Call ``event`` (``before_train``, ``before_step``, ``after_step``, ``after_train``) on every hook."""
        for hook in self.hooks:
            getattr(hook, event)(self)


class Hook:
    """A lifecycle hook: override the moments it acts at."""

    def before_train(self, loop: Loop) -> None:
        """Once, before the first step of this process's run (a resumed run too)."""

    def before_step(self, loop: Loop) -> None:
        """Before each optimizer step (``loop.step`` steps are finished)."""

    def after_step(self, loop: Loop) -> None:
        """After each optimizer step (``loop.step`` counts finished steps; ``loop.values`` what it logged)."""

    def after_evaluation(self, loop: Loop, scores: dict[str, Any]) -> None:
        """After each evaluation on the validation split."""

    def after_train(self, loop: Loop) -> None:
        """Once, after the last step (also when a run stops early on request)."""

    def after_publish(self, loop: Loop, summary: dict[str, Any]) -> None:
        """Once, when a finished stage's ``summary.json`` and report (``report.md`` and its plots) are written, by
        the main process (not after a run stopped early)."""

    def after_abort(self, loop: Loop, error: BaseException) -> None:
        """Once, when the stage ends on an exception after ``before_train``: a failure (a non-finite loss, any
        error) or a stop (SIGTERM, Ctrl-C: ``KeyboardInterrupt``; ``last.pt`` at ``loop.saved`` is kept)."""


class LogHook(Hook):
    """Training values to ``metrics.jsonl`` every ``log_every`` steps and at the last step."""

    def after_step(self, loop: Loop) -> None:
        if loop.step % loop.spec.log_every == 0 or loop.step == loop.total:
            loop.log({"step": loop.step, "epoch": loop.epoch, **loop.values, "time": time.perf_counter() - loop.t0})


class ProgressHook(Hook):
    """The caller's progress callback (a progress bar): step, total, values."""

    def __init__(self, on_step: Callable[[int, int, dict[str, float]], None]) -> None:
        self.on_step = on_step

    def after_step(self, loop: Loop) -> None:
        self.on_step(loop.step, loop.total, loop.values)


class EvalHook(Hook):
    """Validation every ``eval_every`` steps and at the end; a better score writes ``best.pt``."""

    def __init__(self, key: str, higher_is_better: bool) -> None:
        self.key, self.higher = key, higher_is_better

    def after_step(self, loop: Loop) -> None:
        loop.evaluated = loop.step % loop.eval_every == 0 or loop.step == loop.total
        if loop.evaluated:
            loop.evaluate()

    def after_evaluation(self, loop: Loop, scores: dict[str, Any]) -> None:
        loop.log({"step": loop.step, "eval": scores})
        score, best = scores[self.key], loop.best
        if best["scores"] is None or (score > best["score"] if self.higher else score < best["score"]):
            loop.best = {"score": score, "step": loop.step, "scores": scores}
            loop.save("best")


class CheckpointHook(Hook):
    """``last.pt`` at every evaluation, every ``checkpoint_every`` steps and at the last step (model, optimizers, RNG,
    best)."""

    def after_step(self, loop: Loop) -> None:
        if loop.evaluated or loop.step % loop.spec.checkpoint_every == 0 or loop.step == loop.total:
            loop.save("last")


__all__ = ["CheckpointHook", "EvalHook", "Hook", "LogHook", "Loop", "ProgressHook"]
