"""The pipeline: stages in dependency order, each cached by its identity (:mod:`distilkit.engine.store.identity`: the
non-default values of its resolved configuration, the data's fingerprint, the seed, the code versions and the
identities of the stages it reads). ``runs/<recipe>/<stage>-<hash>/summary.json`` marks a finished stage, which is
reused; an unfinished one resumes from ``last.pt``. ``rerun`` retrains named stages (and the
stages downstream of them) on purpose; the replaced folder is kept beside the new one. What the stages share (the
resolved recipe, the data, the upstream weights) is its base, :class:`~distilkit.engine.train.context.RecipeRun`.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

from typing import TYPE_CHECKING

from distilkit.engine.assemble.resolved import ResolvedRecipe
from distilkit.engine.store.summary import read_summary
from distilkit.engine.train.context import RecipeRun
from distilkit.errors import RecipeError
from distilkit.recipe import needed_stages

if TYPE_CHECKING:  # a stage's run imports torch; planning (sweep --plan) builds pipelines without it
    from distilkit.engine.train.stage import StageResult


def writable(root: Path) -> None:
    """Make the recipe's output folder (a read-only one that exists is left as it is: its finished stages are only
    read; a stage that must be written there stops with one line)."""
    from distilkit.errors import DataError

    try:
        root.mkdir(parents=True, exist_ok=True)
    except PermissionError:
        if not root.is_dir():
            raise DataError(f"{root}: cannot create the output folder (permission denied); give --output a "
                            "writable folder") from None


def downstream(res: ResolvedRecipe, names: set[str]) -> set[str]:
    """``names`` and every stage that reads one of them (:meth:`~distilkit.recipe.StageSpec.edges`), transitively."""
    out = set(names)
    for name in res.order:  # dependency order: an upstream stage comes first
        if out & set(res.stages[name].spec.edges().values()):
            out.add(name)
    return out


class Pipeline(RecipeRun):
    """Runs a recipe: resolves it, builds data lazily, trains or reuses each stage, writes a report."""

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
        from distilkit.engine.assemble.devices import stage_devices
        from distilkit.engine.train.cpus import apply_threads
        from distilkit.engine.train.distributed import world_from_env

        apply_threads(self.recipe.threads)  # --threads, the recipe's, OMP_NUM_THREADS, Slurm's, the affinity mask
        if only:
            self.check_stages("--stage", only)
        self.world = world_from_env(stage_devices(self.recipe, only))
        if not self.world.main:  # one process prints and writes
            from distilkit.console import make_console

            self.console = make_console(quiet=True)
        names = needed_stages(self.recipe, set(only)) if only else set(self.resolved.order)
        self.wait = wait  # also for the teacher store's build (teacher_store)
        results = self._run(stop_after, rerun, names, wait)
        if report and not only and len(results) == len(self.resolved.order) and self.world.main:
            from distilkit.report.recipe import write_report

            write_report(self, results)
        elif report and only and results and self.world.main:
            self._show_stages(results, only)
        self.world.finish()
        return results

    def _show_stages(self, results: list[StageResult], only: list[str]) -> None:
        """``--stage``: no recipe report (it would describe part of the recipe), but the scores of the stages run
        or reused (the table a whole run prints) and where each named stage's report is."""
        from distilkit.report.recipe import results_table

        self.console.print(results_table(results))
        for result in results:
            if result.name in only:
                report = result.run_dir / "report.md"
                where = report if report.is_file() else f"{result.run_dir} (no report.md there)"
                self.console.print(f"stage [bold]{result.name}[/] report: {where}", highlight=False, soft_wrap=True)

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
        from distilkit.engine.store.lock import lock_path, stage_lock
        from distilkit.repro import deterministic_algorithms

        from distilkit.engine.train.stage import StageRun

        results: list[StageResult] = []
        again = self.rerun_set(rerun)
        writable(self.root)
        for name in self.resolved.order:
            if name not in names:
                continue
            run_dir = self.run_dir(name)
            if name not in again and read_summary(run_dir) is not None and not os.access(run_dir, os.W_OK):
                results.append(StageRun(self, name, run_dir, stop_after).run())  # finished, read-only: no lock
                continue
            lock = stage_lock(lock_path(self.root, run_dir.name), wait=wait,
                              on_wait=lambda holder, n=name: self.console.print(
                                  f"stage [bold]{n}[/] is being trained by another distilkit run ({holder}); waiting"))
            with lock if self.world.main else contextlib.nullcontext():  # the writing process holds it
                if name in again and run_dir.exists() and self.world.main:
                    self._replace(name, run_dir)
                self.world.barrier()  # the others look at the stage's folder once it is settled
                with deterministic_algorithms():  # bitwise-repeatable (DISTILKIT_DETERMINISTIC=0: off)
                    result = StageRun(self, name, run_dir, stop_after).run()
            if result is None:  # stopped early on request (--stop-after)
                return results
            results.append(result)
        return results
