"""What every experiment tracker shares: the run's identity, the values and their steps, the files at the end.

A tracker is a lifecycle hook (:class:`~distilkit.engine.hooks.Hook`) that implements :meth:`Tracker.start`,
:meth:`Tracker.held`, :meth:`Tracker.scalars`, :meth:`Tracker.flush`, :meth:`Tracker.files`,
:meth:`Tracker.summary` and :meth:`Tracker.finish`; :class:`Tracker` calls them at the loop's moments, in the main
process only (rank 0 of torchrun or DDP; each task of a Slurm array is a run of its own):

* ``before_train``: :meth:`~Tracker.start` with the stage run's :class:`RunIdentity` (recipe, stage, identity
  hash, seed, sweep, variant) and its resolved configuration (``recipe.resolved.yaml``); the tracker's own run id
  is kept in the stage's folder (``trackers.json``), so a resumed stage continues that run. A resumed stage then
  asks the tracker what it holds (:meth:`~Tracker.held`) and logs again, from ``metrics.jsonl``, the steps up to
  the checkpoint it lacks (a killed process's values that never reached it), and never a step it holds;
* ``after_step`` / ``after_evaluation``: ``train/<key>`` for every value the step logged (each weighted term, the
  task loss, the total, the learning rate, an EMA teacher's momentum) every ``every`` steps (0: ``train.log_every``)
  and at the last; ``val/<key>`` for every validation score at the step it was taken (a per-class score as
  ``val/<key>/<class>``; the evaluation's ``seconds_per_sample`` is a timing, ``time/val_seconds_per_sample``, not
  a score). A step's values reach the tracker in one call once a checkpoint (``last.pt``) covers the step: a
  resume starts from a checkpoint, so nothing the tracker holds is ever trained, and logged, again;
* ``after_publish``: the report and its plots, ``summary.json`` and ``recipe.resolved.yaml`` as files, the final
  scores as summary values (``test/best/<key>``, ``test/last/<key>``, ``best_val/<key>``, ``best_step``), then
  :meth:`~Tracker.finish` as ``finished``;
* ``after_train`` before the last step (``--stop-after``) or ``after_abort`` on SIGTERM or Ctrl-C:
  :meth:`~Tracker.finish` as ``stopped`` (``last.pt`` is kept, a resume continues the run); ``after_abort`` on any
  other exception (a non-finite loss, an error): ``failed``.

No tracker moment is fatal: a tracker whose library raises is one warning line (on the console and in
``metrics.jsonl``), is finished as failed where it can be and logs nothing more for the stage; training, the
report and the remaining stages go on (``metrics.jsonl`` keeps every value, and a resume fills in what the tracker
lacks). What ``validate`` can know beforehand is refused there: a missing library, MLflow's store needs, W&B's
login. The libraries' own console output is kept out of distilkit's (:func:`quiet`).

These are exactly the values and steps the ``tensorboard`` tracker writes (it is one of them). A sweep's runs carry
its name from the environment ``distilkit sweep`` sets for them (:data:`SWEEP_ENV`, :data:`VARIANTS_ENV`).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import yaml

from distilkit.cards.trackers import TrackerParams, missing
from distilkit.engine.hooks import Hook, Loop
from distilkit.engine.train.trackers.values import (TIMINGS, final_values, flatten, kept_values, numbers,
                                                    score_values)
from distilkit.files import atomic_write_text

SWEEP_ENV = "DISTILKIT_SWEEP"  # the sweep a run belongs to (its name), set by `distilkit sweep` for its runs
VARIANTS_ENV = "DISTILKIT_SWEEP_VARIANTS"  # the sweep's variants, comma-separated (the other stages are upstream)
IDS_FILE = "trackers.json"  # in the stage's run folder: tracker -> the id of its run, for a resume


def sweep_env(sweep: str, variants: list[str]) -> dict[str, str]:
    """The environment that tells a run's trackers it belongs to sweep ``sweep`` (``distilkit sweep`` gives it to
    every run it starts: in its process, in local processes, in the Slurm jobs it submits)."""
    return {SWEEP_ENV: sweep, VARIANTS_ENV: ",".join(variants)}


@contextlib.contextmanager
def in_sweep(sweep: str, variants: list[str]) -> Iterator[None]:
    """:func:`sweep_env` set in this process's environment for the duration, then restored."""
    values = sweep_env(sweep, variants)
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """A tracker library's console output (Trackio's and MLflow's prints, MLflow's log lines) kept out of
    distilkit's for the duration: what the user asked for (``-q``, a table) is all that is printed."""
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        yield


def setting(value: Any, env: str | None, default: Any = None) -> Any:
    """What to pass the library for one setting: None where its environment variable ``env`` is set (the library
    reads it: the machine's setting is honoured, never overridden), else the recipe's ``value``, else ``default``."""
    if env is not None and os.environ.get(env):
        return None
    return value if value is not None else default


@dataclass(frozen=True)
class RunIdentity:
    """Who a stage run is, for a tracker: its recipe, stage, identity hash and seed, its folder, the sweep and the
    variant it belongs to (a sweep's upstream stage, its teacher, has no variant), and its resolved configuration."""

    recipe: str
    stage: str
    hash: str
    seed: int
    run_dir: Path
    config: dict[str, Any] = field(default_factory=dict)
    sweep: str | None = None
    variant: str | None = None

    @classmethod
    def of(cls, run_dir: Path, stage: str) -> "RunIdentity":
        """Read from the stage's ``recipe.resolved.yaml`` and the sweep's environment variables."""
        config = yaml.safe_load((run_dir / "recipe.resolved.yaml").read_text(encoding="utf-8")) or {}
        sweep = os.environ.get(SWEEP_ENV) or None
        variants = [v for v in os.environ.get(VARIANTS_ENV, "").split(",") if v]
        return cls(str(config.get("recipe", run_dir.parent.name)), stage, str(config.get("hash", "")),
                   int(config.get("seed", 0)), run_dir, config, sweep,
                   stage if sweep is not None and stage in variants else None)

    @property
    def group(self) -> str:
        """What the tracker groups the run under: the sweep, else the recipe."""
        return self.sweep or self.recipe

    @property
    def name(self) -> str:
        """The run's display name: ``<variant>-seed<seed>`` in a sweep, else its folder's name (``<stage>-<hash>``)."""
        return f"{self.variant}-seed{self.seed}" if self.variant else self.run_dir.name

    @property
    def sweep_root(self) -> Path:
        """The sweep's folder (its runs' folders are in it; ``results.md`` is written there)."""
        return self.run_dir.parent

    def tags(self) -> dict[str, str]:
        """The identity as ``distilkit.*`` tags (a sweep's runs: also ``sweep``, ``variant`` or ``role: upstream``,
        and where the sweep's table with its paired intervals is written)."""
        out = {"distilkit.recipe": self.recipe, "distilkit.stage": self.stage, "distilkit.hash": self.hash,
               "distilkit.seed": str(self.seed), "distilkit.run_dir": str(self.run_dir.resolve())}
        if self.sweep is not None:
            out.update({"distilkit.sweep": self.sweep, "distilkit.role": "variant" if self.variant else "upstream",
                        "distilkit.sweep_report": str((self.sweep_root / "results.md").resolve())})
            if self.variant is not None:
                out["distilkit.variant"] = self.variant
        return out

    def full_config(self) -> dict[str, Any]:
        """The resolved configuration with the identity beside it (``distilkit``: recipe, stage, seed, sweep,
        variant, ...): what a tracker's table compares runs by."""
        return {**self.config, "distilkit": {k.split(".", 1)[1]: v for k, v in self.tags().items()}}


def report_files(run_dir: Path) -> list[Path]:
    """What a finished stage's tracker run gets as files: the report, its plots, the summary and the resolved
    configuration (those that exist)."""
    named = [run_dir / n for n in ("report.md", "summary.json", "recipe.resolved.yaml")]
    return [p for p in [*named, *sorted(run_dir.glob("*.png"))] if p.is_file()]


def read_ids(run_dir: Path) -> dict[str, Any]:
    path = run_dir / IDS_FILE
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def one_line(error: BaseException, limit: int = 300) -> str:
    """An exception as one line: its type where its text does not say much, the first line of its text."""
    text = (str(error).strip().splitlines() or [""])[0]
    text = text if len(text) <= limit else text[:limit - 1] + "…"
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


class Tracker(Hook):
    """An experiment tracker: a hook that maps the loop's moments onto :meth:`start`, :meth:`held`,
    :meth:`scalars`, :meth:`flush`, :meth:`files`, :meth:`summary` and :meth:`finish` (override those) in the
    main process; it keeps a step's values until a checkpoint covers the step, and keeps the library's failures
    from the stage (one warning each)."""

    key = "tracker"  # its entry in trackers.json

    def __init__(self, params: TrackerParams) -> None:
        self.params = params
        self.active = False
        self.identity: RunIdentity | None = None
        self.loop: Loop | None = None
        self.pending: dict[int, dict[str, float]] = {}  # values of steps no checkpoint covers yet
        self.floor = 0  # the tracker's run holds every step up to here: none of them is logged again
        self.every = 1

    # -- what a tracker implements ----------------------------------------------------------------------------
    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        """Open the tracker's run, or continue the one ``resume`` names (kept in ``trackers.json``: the stage
        resumes, ``step`` steps are done); call :meth:`keep` with what names it before logging anything."""

    def held(self, step: int) -> int:
        """The last step of which the run holds every value (read from the library's store): the resumed stage
        (``step`` steps done) logs again, from ``metrics.jsonl``, the steps after it up to ``step``. By default
        ``step``: nothing is logged again."""
        return step

    def scalars(self, values: dict[str, float], step: int) -> None:
        """Log ``values`` (``train/...``, ``val/...``, ``time/...``: all of the step's) at ``step``."""

    def flush(self, step: int) -> None:
        """Every step up to ``step`` has been handed to :meth:`scalars`: make it durable where the library
        buffers."""

    def files(self, paths: list[Path]) -> None:
        """Attach the finished stage's files (report, plots, summary)."""

    def summary(self, values: dict[str, Any]) -> None:
        """Record the final scores as the run's summary values."""

    def finish(self, status: str, why: str = "") -> None:
        """Close the run as ``finished``; ``stopped`` (SIGTERM, Ctrl-C, ``--stop-after``: ``last.pt`` is kept
        and a resume continues the run); or ``failed`` (``why``: the error, in one line)."""

    # -- kept between processes --------------------------------------------------------------------------------
    def keep(self, value: Any) -> None:
        """Write what names this tracker's run to the stage's ``trackers.json`` (read back on a resume)."""
        assert self.identity is not None
        ids = read_ids(self.identity.run_dir)
        ids[self.key] = value
        atomic_write_text(self.identity.run_dir / IDS_FILE, json.dumps(ids, indent=1))

    def warn(self, text: str) -> None:
        """One line for the user, through the loop (the stage's console and ``metrics.jsonl``)."""
        if self.loop is not None:
            self.loop.warn(text)
        else:
            print(f"warning: {text}", file=sys.stderr)

    # -- failures: one warning, never the stage's end ----------------------------------------------------------
    @contextlib.contextmanager
    def guarded(self, what: str, fatal: bool = True) -> Iterator[None]:
        """The library's exception in the block becomes one warning; ``fatal``: the tracker logs nothing more for
        the stage (its run finished as failed where it can be)."""
        try:
            yield
        except Exception as exc:  # noqa: BLE001  a tracker's failure is never the stage's
            stage = self.identity.stage if self.identity is not None else "?"
            more = f"; it logs nothing more for stage {stage} (metrics.jsonl keeps every value)" if fatal else ""
            self.warn(f"the {self.key} tracker failed ({what}): {one_line(exc)}{more}")
            if fatal and self.active:
                self.active = False
                self.pending.clear()
                with contextlib.suppress(Exception):
                    self.finish("failed", one_line(exc))

    # -- the loop's moments -------------------------------------------------------------------------------------
    def before_train(self, loop: Loop) -> None:
        if not loop.main:
            return
        self.loop = loop
        self.identity = RunIdentity.of(loop.run_dir, loop.stage)
        self.every = self.params.every or loop.spec.log_every
        with self.guarded("start"):
            self.active = True
            self.start(self.identity, read_ids(loop.run_dir).get(self.key), loop.step)
            held = self.held(loop.step)
            self.floor = max(held, loop.step)  # beyond the checkpoint (it was unreadable): kept as logged
            if held < loop.step:  # what a killed process handed the library and it never wrote
                self.deliver(kept_values(loop.run_dir, held, loop.step, self.every, loop.total, loop.per_class))

    def after_step(self, loop: Loop) -> None:
        if not self.active:
            return
        if loop.step > self.floor and (loop.step % self.every == 0 or loop.step == loop.total):
            self.pending.setdefault(loop.step, {}).update({f"train/{k}": v for k, v in numbers(loop.values).items()})
        self.deliver_saved(loop)

    def after_evaluation(self, loop: Loop, scores: dict[str, Any]) -> None:
        if self.active and loop.step > self.floor:
            self.pending.setdefault(loop.step, {}).update(score_values(scores, "val", loop.per_class))

    def deliver_saved(self, loop: Loop) -> None:
        """Log the pending steps the last checkpoint covers (``loop.saved``)."""
        ready = {step: self.pending.pop(step) for step in sorted(self.pending) if step <= loop.saved}
        if ready:
            with self.guarded("logging"):
                self.deliver(ready)

    def deliver(self, steps: dict[int, dict[str, float]]) -> None:
        """Each step's values in one call, in step order, then :meth:`flush`."""
        for step, values in sorted(steps.items()):
            if values:
                self.scalars(values, step)
        if steps:
            self.flush(max(steps))

    def end(self, status: str, why: str = "") -> None:
        """Finish the run (once) as ``status``; values no checkpoint covers are dropped (a resume logs them)."""
        if not self.active:
            return
        self.pending.clear()
        self.active = False
        with self.guarded("finish", fatal=False):
            self.finish(status, why)

    def after_train(self, loop: Loop) -> None:
        if self.active:
            self.deliver_saved(loop)
        if loop.step < loop.total:  # --stop-after: the checkpoint is kept, a resume continues
            self.end("stopped", f"stopped after step {loop.step} (--stop-after); resumable from step {loop.saved}")

    def after_abort(self, loop: Loop, error: BaseException) -> None:
        if not self.active:
            return
        self.deliver_saved(loop)
        if isinstance(error, KeyboardInterrupt):  # SIGTERM (the loop wrote last.pt first) or Ctrl-C
            self.end("stopped", f"stopped at step {loop.step} (a signal); resumable from step {loop.saved}")
        else:
            self.end("failed", one_line(error))

    def after_publish(self, loop: Loop, summary: dict[str, Any]) -> None:
        if not self.active:
            return
        self.deliver_saved(loop)
        with self.guarded("final scores", fatal=False):
            self.summary(final_values(summary, loop.per_class))
        with self.guarded("report files", fatal=False):
            self.files(report_files(loop.run_dir))
        self.end("finished")


__all__ = ["IDS_FILE", "RunIdentity", "SWEEP_ENV", "TIMINGS", "Tracker", "TrackerParams", "VARIANTS_ENV",
           "final_values", "flatten", "in_sweep", "kept_values", "missing", "numbers", "one_line", "quiet",
           "read_ids", "report_files", "score_values", "setting", "sweep_env"]
