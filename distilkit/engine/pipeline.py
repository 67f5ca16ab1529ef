"""The pipeline: stages in dependency order, each cached by its identity (:mod:`distilkit.engine.identity`: the
non-default values of its resolved configuration, the data's fingerprint, the seed, the code versions and the
identities of the stages it reads). ``runs/<recipe>/<stage>-<hash>/summary.json`` marks a finished stage, which is
reused; an unfinished one resumes from ``last.pt``. ``rerun`` retrains named stages (and the
stages downstream of them) on purpose; the replaced folder is kept beside the new one.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from distilkit import __version__
from distilkit.engine.io import atomic_write_text
from distilkit.engine.identity import stage_hashes, stage_seed
from distilkit.engine.resolve import ResolvedRecipe, ResolvedStage, resolve
from distilkit.errors import RecipeError
from distilkit.recipe import Recipe, load_recipe, needed_stages
from distilkit.registry import DATASETS


@dataclass
class StageResult:
    name: str
    run_dir: Path
    summary: dict[str, Any]
    reused: bool


def downstream(res: ResolvedRecipe, names: set[str]) -> set[str]:
    """``names`` and every stage that reads one of them (:meth:`~distilkit.recipe.StageSpec.edges`), transitively."""
    out = set(names)
    for name in res.order:  # dependency order: an upstream stage comes first
        if out & set(res.stages[name].spec.edges().values()):
            out.add(name)
    return out


def read_summary(run_dir: Path) -> dict[str, Any] | None:
    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return summary if summary.get("status") == "finished" else None


class Pipeline:
    """Runs a recipe: resolves it, builds data lazily, trains or reuses each stage, writes a report."""

    def __init__(self, recipe: Recipe | str | Path, output: str | Path = "runs", console: Any = None,
                 quiet: bool = False, seed: int | None = None, overrides: dict[str, Any] | None = None) -> None:
        self.source = str(recipe) if not isinstance(recipe, Recipe) else "recipe"
        if overrides and isinstance(recipe, Recipe):
            raise ValueError("overrides apply to a recipe file; change a Recipe object with model_copy")
        self.recipe = recipe if isinstance(recipe, Recipe) else load_recipe(recipe, overrides)
        self.overrides = dict(overrides or {})  # recorded beside each stage's resolved configuration
        if seed is not None:  # a seed from the command line: a different identity for every stage
            self.recipe = self.recipe.model_copy(update={"seed": seed})
        self.resolved = resolve(self.recipe, self.source)
        self.root = Path(output) / self.recipe.name
        self.hashes, self.configs = stage_hashes(self.resolved)
        self.quiet = quiet
        if console is None:
            from distilkit.console import make_console

            console = make_console(quiet=quiet)
        self.console = console
        self._data: dict[str, Any] = {}  # split -> dataset
        from distilkit.engine.distributed import SINGLE

        self.world = SINGLE  # the processes of this run: set in run() from torchrun's environment

    def share_data(self, store: dict[str, dict[str, Any]]) -> None:
        """Share datasets with the other pipelines in ``store`` that have the same data configuration (a sweep's
        runs read their scenes once)."""
        key = json.dumps({"dataset": self.recipe.data.dataset,
                          "params": self.resolved.data_params.model_dump(mode="json")}, sort_keys=True)
        self._data = store.setdefault(key, self._data)

    def run_dir(self, name: str) -> Path:
        return self.root / f"{name}-{self.hashes[name]}"

    def dataset(self, split: str) -> Any:
        if split not in self._data:
            entry = DATASETS.entry(self.recipe.data.dataset)
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            with Progress(TextColumn(f"[cyan]data[/] {self.recipe.data.dataset}/{split}"), BarColumn(),
                          MofNCompleteColumn(), TimeRemainingColumn(), console=self.console, transient=True) as prog:
                task = prog.add_task("gen", total=None)
                self._data[split] = entry.obj(self.resolved.data_params, split,
                                              lambda i, n: prog.update(task, completed=i, total=n))
        return self._data[split]

    def _teacher_checkpoint(self, stage: ResolvedStage) -> Path:
        t = stage.spec.teacher
        assert t is not None
        if t.from_ is not None:
            return self.run_dir(t.from_) / "checkpoints" / f"{t.which}.pt"
        return Path(t.checkpoint or "").expanduser()

    @property
    def collate(self) -> Any:
        """The dataset's registered collate (samples -> :class:`~distilkit.data.batch.Batch`)."""
        return DATASETS.entry(self.recipe.data.dataset).meta["collate"]

    def _init(self, stage: ResolvedStage) -> tuple[Path, bool] | None:
        """The weights file a stage's student starts from, and whether all must fit."""
        init = stage.spec.init
        if init is None:
            return None
        if init.from_ is not None:
            return self.run_dir(init.from_) / "checkpoints" / f"{init.which}.pt", init.strict
        return Path(init.checkpoint or "").expanduser(), init.strict

    def has_split(self, split: str) -> bool:
        entry = DATASETS.entry(self.recipe.data.dataset)
        return bool(entry.meta.get("has_split", lambda p, s: s != "test")(self.resolved.data_params, split))

    def check_stages(self, option: str, names: list[str]) -> None:
        """A one-line RecipeError for stage names (from ``option``) that the recipe does not have."""
        unknown = [n for n in names if n not in self.resolved.stages]
        if unknown:
            import difflib

            hints = "".join(f"; did you mean {c[0]!r}?" for n in unknown
                            if (c := difflib.get_close_matches(n, list(self.resolved.stages), n=1)))
            raise RecipeError([("", f"{option}: no stage named {', '.join(map(repr, unknown))}{hints} "
                                    f"(stages: {', '.join(self.resolved.order)})")], self.source)

    def rerun_set(self, names: list[str] | None) -> set[str]:
        """The stages ``--rerun`` names, checked, plus every stage downstream of them."""
        if not names:
            return set()
        self.check_stages("--rerun", names)
        return downstream(self.resolved, set(names))

    def run(self, stop_after: int | None = None, rerun: list[str] | None = None, only: list[str] | None = None,
            report: bool = True, wait: bool = True) -> list[StageResult]:
        """Train what is not finished, in dependency order, and write the report.

        ``only``: just these stages and the stages they need (then no recipe report is written: it would
        describe part of the recipe). A stage another process is training is waited for and then reused
        (``wait=False``: :class:`~distilkit.errors.RunLockedError` instead)."""
        from distilkit.engine.distributed import world_from_env

        if only:
            self.check_stages("--stage", only)
        self.world = world_from_env()
        if not self.world.main:  # one process prints and writes
            from distilkit.console import make_console

            self.console = make_console(quiet=True)
        names = needed_stages(self.recipe, set(only)) if only else set(self.resolved.order)
        results = self._run(stop_after, rerun, names, wait)
        if report and not only and len(results) == len(self.resolved.order) and self.world.main:
            from distilkit.report.recipe import write_report

            write_report(self, results)
        return results

    def _replace(self, name: str, run_dir: Path) -> None:
        """Move a stage's finished run aside (``--rerun``): kept beside the new one."""
        stamp, n = time.strftime("%Y%m%d-%H%M%S"), 1
        kept = run_dir.with_name(f"{run_dir.name}.replaced-{stamp}")
        while kept.exists():
            n += 1
            kept = run_dir.with_name(f"{run_dir.name}.replaced-{stamp}-{n}")
        run_dir.rename(kept)
        self.console.print(f"stage [bold]{name}[/] retrained on request; the previous run is kept in {kept}")

    def _run(self, stop_after: int | None, rerun: list[str] | None, names: set[str],
             wait: bool) -> list[StageResult]:
        from distilkit.engine.lock import lock_path, stage_lock
        from distilkit.repro import deterministic_algorithms

        results: list[StageResult] = []
        again = self.rerun_set(rerun)
        self.root.mkdir(parents=True, exist_ok=True)
        for name in self.resolved.order:
            if name not in names:
                continue
            run_dir = self.run_dir(name)
            lock = stage_lock(lock_path(self.root, run_dir.name), wait=wait,
                              on_wait=lambda holder, n=name: self.console.print(
                                  f"stage [bold]{n}[/] is being trained by another distilkit run ({holder}); waiting"))
            with lock if self.world.main else contextlib.nullcontext():  # the writing process holds it
                if name in again and run_dir.exists() and self.world.main:
                    self._replace(name, run_dir)
                self.world.barrier()  # the others look at the stage's folder once it is settled
                with deterministic_algorithms():  # bitwise-repeatable (DISTILKIT_DETERMINISTIC=0: off)
                    result = self._stage(name, run_dir, stop_after)
            if result is None:  # stopped early on request (--stop-after)
                return results
            results.append(result)
        return results

    def _stage(self, name: str, run_dir: Path, stop_after: int | None) -> StageResult | None:
        """Reuse a finished stage or train and evaluate it (the caller holds its lock)."""
        import torch

        from distilkit.engine.io import seed_everything
        from distilkit.engine.memory import is_out_of_memory, out_of_memory
        from distilkit.engine.models import load_teacher, pick_device
        from distilkit.console import stage_progress
        from distilkit.engine.trainer import Trainer, write_summary

        stage = self.resolved.stages[name]
        done = read_summary(run_dir)
        if done is not None:
            self.console.print(f"[green]✓[/] stage [bold]{name}[/] reused from {run_dir}")
            # the label is cosmetic (not part of the identity): show the recipe's current one
            return StageResult(name, run_dir, {**done, "label": stage.spec.label or name}, reused=True)
        cfg = self.configs[name]
        seed = stage_seed(self.resolved, stage)
        if self.world.main:
            run_dir.mkdir(parents=True, exist_ok=True)
            for stale in [*run_dir.glob(".*"), *run_dir.glob("checkpoints/.*")]:  # a killed writer's temporary files
                stale.unlink(missing_ok=True)
            atomic_write_text(run_dir / "recipe.resolved.yaml",
                              yaml.safe_dump({"recipe": self.recipe.name, "stage": name, "hash": self.hashes[name],
                                              "distilkit": __version__,
                                              **({"overrides": self.overrides} if self.overrides else {}), **cfg},
                                             sort_keys=False))
        seed_everything(seed)
        device = pick_device(stage.spec.train.device)
        teacher = None
        if stage.teacher is not None and stage.distill:
            teacher = load_teacher(stage.teacher, self.resolved.data_info, self._teacher_checkpoint(stage), device)
        train_set, val_set = self.dataset("train"), self.dataset("val")
        trainer: Trainer | None = None
        try:
            with stage_progress(self.console, name) as on_step:
                trainer = Trainer(stage, self.resolved.data_info, train_set, val_set, run_dir, seed,
                                  teacher, on_step, stop_after, collate=self.collate, init=self._init(stage),
                                  world=self.world)
                result = trainer.fit()
            if stop_after is not None and result.steps < trainer.total_steps:
                self.console.print(f"stage {name} stopped after {result.steps} steps (checkpoint kept)")
                return None
            split = "test" if self.has_split("test") else "val"
            best = trainer.best_model()  # read once: scored on the test split, previewed on a validation scene
            test = trainer.evaluate_checkpoints(self.dataset(split), best)
            trainer.write_preview(val_set, best)
        except (RuntimeError, MemoryError) as exc:  # out of memory: one line that says what to lower
            if not is_out_of_memory(exc):
                raise
            kept = trainer.kept() if trainer is not None else "no checkpoint had been written yet"
            raise out_of_memory(stage, self.resolved.data_info, exc, kept) from None
        summary = {
            "status": "finished", "stage": name, "hash": self.hashes[name], "label": stage.spec.label or name,
            "adapter": stage.student.adapter, "input": stage.student.cls.describe(stage.student.params),
            "teacher": stage.teacher_from or (stage.spec.teacher.checkpoint if stage.spec.teacher else None),
            "objectives": [f"{t.name}×{t.weight:g}" for t in stage.distill], "seed": seed,
            "processes": self.world.size, "threads": torch.get_num_threads(),  # rounding depends on them
            "deterministic": torch.are_deterministic_algorithms_enabled(),
            "classes": {"names": list(self.resolved.data_info.classes.names),
                        "colours": [list(c) for c in self.resolved.data_info.classes.colours]},
            "steps": result.steps, "train_seconds": round(result.seconds, 2),
            "metric": {"name": stage.metric.name, "key": stage.metric.key} if stage.metric else None,
            "best": result.best, "last": result.last, "report_split": split, "test": test,
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S"),
        }
        if not self.world.main:
            return StageResult(name, run_dir, summary, reused=False)
        write_summary(run_dir, summary)
        try:
            from distilkit.report.run import write_run_report

            write_run_report(run_dir)
        except Exception as exc:  # a plotting problem must not lose a finished stage
            self.console.print(f"[yellow]{run_dir / 'report.md'} not written: {exc}[/]")
        return StageResult(name, run_dir, summary, reused=False)
