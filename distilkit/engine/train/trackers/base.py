"""What every experiment tracker shares: the run's identity, the values and their steps, the files at the end.

A tracker is a lifecycle hook (:class:`~distilkit.engine.hooks.Hook`) that implements five operations —
:meth:`Tracker.start`, :meth:`Tracker.scalars`, :meth:`Tracker.files`, :meth:`Tracker.summary` and
:meth:`Tracker.finish` — and :class:`Tracker` calls them at the loop's moments, in the main process only (rank 0
of torchrun or DDP; each task of a Slurm array is a run of its own):

* ``before_train``: :meth:`~Tracker.start` with the stage run's :class:`RunIdentity` (recipe, stage, identity
  hash, seed, sweep, variant) and its resolved configuration (``recipe.resolved.yaml``); the tracker's run id is
  kept in the stage's folder (``trackers.json``) before anything is logged, so a resumed stage continues that run;
* ``after_step``: ``train/<key>`` for every value the step logged (each weighted term, the task loss, the total,
  the learning rate, an EMA teacher's momentum) every ``every`` steps (0: ``train.log_every``) and at the last;
* ``after_evaluation``: ``val/<key>`` for every numeric validation score, at the step it was taken;
* ``after_publish``: the report and its plots, ``summary.json`` and ``recipe.resolved.yaml`` as files, the final
  scores as summary values (``test/best/<key>``, ``test/last/<key>``, ``best_val/<key>``, ``best_step``), then
  :meth:`~Tracker.finish`; a run stopped early (a signal, ``--stop-after``) is finished as stopped.

These are exactly the values and steps the ``tensorboard`` tracker writes (it is one of them). A sweep's runs carry
its name from the environment ``distilkit sweep`` sets for them (:data:`SWEEP_ENV`, :data:`VARIANTS_ENV`).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import yaml
from pydantic import BaseModel, ConfigDict, Field

from distilkit.engine.hooks import Hook, Loop
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


class TrackerParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    every: int = Field(0, ge=0, description="log training values every N steps (0: as often as log_every)")


def missing(module: str, extra: str, tracker: str) -> str | None:
    """None when ``module`` can be imported (looked up, not imported), else the line that says what to install."""
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        found = False
    return None if found else (f"the {tracker} tracker needs the {module} package, which is not installed; "
                               f"pip install 'distilkit[{extra}]'")


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


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings as ``a/b/c`` keys (lists stay values)."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out.update(flatten(value, f"{prefix}/{key}" if prefix else str(key)))
    return out


def numbers(values: dict[str, Any]) -> dict[str, float]:
    """The numeric values (numbers and one-element tensors; not booleans, strings or mappings) as floats."""
    out = {}
    for key, value in values.items():
        if isinstance(value, (bool, str, bytes, dict, list, tuple)) or value is None:
            continue
        try:
            out[key] = float(value)
        except (TypeError, ValueError, RuntimeError):
            continue
    return out


def final_values(summary: dict[str, Any]) -> dict[str, Any]:
    """A finished stage's scores as summary values: ``test/best/<key>`` and ``test/last/<key>`` on the report
    split, ``best_val/<key>`` at the best validation step, ``best_step``, ``steps``, ``report_split``."""
    test = summary.get("test") or {}
    best = summary.get("best") or {}
    out: dict[str, Any] = {}
    for which in ("best", "last"):
        out.update({f"test/{which}/{k}": v for k, v in numbers(test.get(which) or {}).items()})
    out.update({f"best_val/{k}": v for k, v in numbers(best.get("scores") or {}).items()})
    out.update({"best_step": best.get("step"), "steps": summary.get("steps"),
                "report_split": summary.get("report_split")})
    return {k: v for k, v in out.items() if v is not None}


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


class Tracker(Hook):
    """An experiment tracker: a hook that maps the loop's moments onto :meth:`start`, :meth:`scalars`,
    :meth:`files`, :meth:`summary` and :meth:`finish` (override those) in the main process."""

    key = "tracker"  # its entry in trackers.json

    def __init__(self, params: TrackerParams) -> None:
        self.params = params
        self.active = False
        self.identity: RunIdentity | None = None

    # -- what a tracker implements ----------------------------------------------------------------------------
    def start(self, identity: RunIdentity, resume: Any, step: int) -> None:
        """Open the tracker's run, or continue the one ``resume`` names (kept in ``trackers.json``: the stage
        resumes, ``step`` steps are done); call :meth:`keep` with what names it before logging anything."""

    def scalars(self, values: dict[str, float], step: int) -> None:
        """Log ``values`` (``train/...`` or ``val/...``) at ``step``."""

    def files(self, paths: list[Path]) -> None:
        """Attach the finished stage's files (report, plots, summary)."""

    def summary(self, values: dict[str, Any]) -> None:
        """Record the final scores as the run's summary values."""

    def finish(self, finished: bool) -> None:
        """Close the run: ``finished``, or stopped early with its checkpoint kept (it will be resumed)."""

    # -- kept between processes --------------------------------------------------------------------------------
    def keep(self, value: Any) -> None:
        """Write what names this tracker's run to the stage's ``trackers.json`` (read back on a resume)."""
        assert self.identity is not None
        ids = read_ids(self.identity.run_dir)
        ids[self.key] = value
        atomic_write_text(self.identity.run_dir / IDS_FILE, json.dumps(ids, indent=1))

    # -- the loop's moments -------------------------------------------------------------------------------------
    def before_train(self, loop: Loop) -> None:
        if not loop.main:
            return
        self.identity = RunIdentity.of(loop.run_dir, loop.stage)
        self.start(self.identity, read_ids(loop.run_dir).get(self.key), loop.step)
        self.active = True

    def after_step(self, loop: Loop) -> None:
        every = self.params.every or loop.spec.log_every
        if self.active and (loop.step % every == 0 or loop.step == loop.total):
            self.scalars({f"train/{k}": v for k, v in numbers(loop.values).items()}, loop.step)

    def after_evaluation(self, loop: Loop, scores: dict[str, Any]) -> None:
        if self.active:
            self.scalars({f"val/{k}": v for k, v in numbers(scores).items()}, loop.step)

    def after_train(self, loop: Loop) -> None:
        if self.active and loop.step < loop.total:  # stopped early: the checkpoint is kept, a resume continues
            self.active = False
            self.finish(False)

    def after_publish(self, loop: Loop, summary: dict[str, Any]) -> None:
        if not self.active:
            return
        self.active = False
        self.summary(final_values(summary))
        self.files(report_files(loop.run_dir))
        self.finish(True)


__all__ = ["IDS_FILE", "RunIdentity", "SWEEP_ENV", "Tracker", "TrackerParams", "VARIANTS_ENV", "final_values",
           "flatten", "in_sweep", "missing", "numbers", "read_ids", "report_files", "setting", "sweep_env"]
