"""Run a sweep: every variant at every seed, upstream stages shared, finished runs reused, then the table.

A run is ``distilkit run <variant recipe> --seed S --stage <variant>`` on the sweep's output folder — in this
process (``jobs=1``), in ``jobs`` parallel processes that split the CPU's threads between them, or on other
machines from the commands of :func:`plan` (then ``distilkit sweep`` only collects). Two processes that need
the same upstream stage take turns on its lock, so it is trained once.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import Any

import yaml

from typing import TYPE_CHECKING

from distilkit.engine.store.summary import read_summary
from distilkit.engine.train.cpus import usable_cpus
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import DistilkitError, RecipeError
from distilkit.files import atomic_write_text
from distilkit.sweep.processes import Children, RunLines
from distilkit.sweep.spec import Sweep, load_sweep
from distilkit.sweep.tasks import Task, missing_text, variants_phrase

if TYPE_CHECKING:  # running and collecting import torch and the reports; --plan needs neither
    from distilkit.sweep.results import RunRecord


class SweepRun:
    """A sweep bound to an output folder and seeds: its tasks, pipelines and finished runs."""

    def __init__(self, sweep: Sweep | str | Path, output: str | Path = "runs", seeds: list[int] | None = None,
                 quiet: bool = False, console: Any = None) -> None:
        self.sweep = sweep if isinstance(sweep, Sweep) else load_sweep(sweep)
        if seeds is not None and len(set(seeds)) != len(seeds):
            raise DistilkitError(f"--seeds: give each seed once, got {' '.join(map(str, seeds))}")
        self.seeds = list(seeds) if seeds else list(self.sweep.spec.seeds)
        self.output = Path(output)
        self.root = self.output / self.sweep.name
        if console is None:
            from distilkit.console import make_console

            console = make_console(quiet=quiet)
        self.console, self.quiet = console, quiet
        self.pipes: dict[tuple[str, int], Pipeline] = {}
        data: dict[str, dict[str, Any]] = {}  # data configuration -> its datasets, generated or read once
        for variant, recipe in self.sweep.recipes.items():  # resolve every variant before anything runs
            for seed in self.seeds:
                try:
                    pipe = Pipeline(recipe, self.output, console=console, quiet=quiet, seed=seed)
                except RecipeError as err:
                    raise RecipeError([(f"variants.{variant}" + (f" (recipe {p})" if p else ""), m)
                                       for p, m in err.problems], self.sweep.source) from None
                pipe.share_data(data)
                self.pipes[variant, seed] = pipe

    def recipe_file(self, variant: str) -> Path:
        return self.root / "recipes" / f"{variant}.yaml"

    def write_recipes(self) -> None:
        """Each variant's recipe as a file (what the planned commands run), and the sweep as resolved."""
        for variant, data in self.sweep.data.items():
            text = yaml.safe_dump(data, sort_keys=False, allow_unicode=True)
            path = self.recipe_file(variant)
            if not path.is_file() or path.read_text(encoding="utf-8") != text:
                atomic_write_text(path, f"# variant {variant!r} of sweep {self.sweep.name} ({self.sweep.source})\n"
                                  + text)

    def upstream_tasks(self) -> list[Task]:
        """One task per distinct set of upstream runs (by identity): with a shared teacher, one in all. Each is named
        by the variants whose runs wait on it (at its seed)."""
        found: dict[tuple[str, ...], tuple[Task, list[str]]] = {}  # upstream runs -> (the task, the variants)
        for seed in self.seeds:
            for variant in self.sweep.recipes:
                names = self.sweep.upstream_stages(variant)
                if not names:
                    continue
                task = Task(variant, seed, tuple(names), self.recipe_file(variant))
                users = found.setdefault(self.upstream_key(task), (task, []))[1]
                if variant not in users:  # a teacher shared over seeds: each variant once
                    users.append(variant)
        every = list(self.sweep.recipes)
        return [replace(task, upstream_of=variants_phrase(users, every)) for task, users in found.values()]

    def upstream_key(self, task: Task) -> tuple[str, ...]:
        """The folders of the upstream runs a task's variant needs at its seed (what one upstream task trains)."""
        pipe = self.pipes[task.variant, task.seed]
        return tuple(sorted(pipe.run_dir(n).name for n in self.sweep.upstream_stages(task.variant)))

    def task(self, variant: str, seed: int, stages: tuple[str, ...]) -> Task:
        return Task(variant, seed, tuple(stages), self.recipe_file(variant))

    def variant_tasks(self) -> list[Task]:
        return [Task(v, s, (v,), self.recipe_file(v)) for s in self.seeds for v in self.sweep.recipes]

    def finished(self, task: Task) -> bool:
        pipe = self.pipes[task.variant, task.seed]
        return all(read_summary(pipe.run_dir(n)) is not None for n in task.stages)

    # -- running -------------------------------------------------------------------------------------------

    def plan(self) -> list[str]:
        """``distilkit run`` command lines: the upstream runs first, then one per variant and seed."""
        self.write_recipes()
        return [shlex.join(["distilkit", *t.argv(self.output)]) for t in self.upstream_tasks() + self.variant_tasks()]

    def run(self, jobs: int = 1) -> list[str]:
        """Run what is not finished; return the failures (``task: message``), the others go on."""
        self.write_recipes()
        todo = [t for t in self.upstream_tasks() + self.variant_tasks() if not self.finished(t)]
        total = len(self.variant_tasks())
        self.console.print(f"sweep [bold]{self.sweep.name}[/]: {len(self.sweep.recipes)} variants × "
                           f"{len(self.seeds)} seeds = {total} runs, {total - sum(t.stages == (t.variant,) for t in todo)}"
                           f" finished; output {self.root}")
        if jobs <= 1:
            return self._in_process(todo)
        return self._in_processes(todo, jobs)

    def _in_process(self, todo: list[Task]) -> list[str]:
        failures = []
        for i, task in enumerate(todo, 1):
            if not self.quiet:
                self.console.rule(f"[{i}/{len(todo)}] {task.title}")
            try:
                from distilkit.engine.train.trackers.base import in_sweep

                with in_sweep(self.sweep.name, list(self.sweep.recipes)):  # for the runs' trackers
                    self.pipes[task.variant, task.seed].run(only=list(task.stages), report=False)
            except DistilkitError as exc:  # one run's failure (a NaN loss) must not stop the others
                failures.append(f"{task.title}: {exc}")
                self.console.print(f"[red]failed:[/] {task.title}: {exc}")
        return failures

    def _in_processes(self, todo: list[Task], jobs: int) -> list[str]:
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        cpus = usable_cpus()
        threads = max(1, cpus // jobs)
        if jobs > cpus:
            self.console.print(f"[yellow]--jobs {jobs} on {cpus} CPUs: jobs share cores (1 thread each)[/]")
        from distilkit.engine.train.stop import PARENT_ENV
        from distilkit.engine.train.trackers.base import sweep_env

        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
               PARENT_ENV: str(os.getpid()),  # a run stops (checkpoint written) if this process dies
               **sweep_env(self.sweep.name, list(self.sweep.recipes))}  # its trackers group it by the sweep
        logs = self.root / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        failures: list[str] = []
        children = Children()

        def one(task: Task) -> tuple[float, bool]:
            """The run's wall-clock seconds, and whether it failed."""
            log = logs / f"{'+'.join(task.stages)}-seed{task.seed}.log"
            start = time.monotonic()
            with open(log, "w", encoding="utf-8") as out:
                code = children.run([sys.executable, "-m", "distilkit", *task.argv(self.output), "--quiet"],
                                    stdout=out, stderr=subprocess.STDOUT, env=env)
            failed = code is not None and code != 0 and not children.stopping
            if failed:
                tail = log.read_text(encoding="utf-8", errors="replace").strip().splitlines()[-1:] or ["(no output)"]
                failures.append(f"{task.title}: exit status {code}: {tail[0]} (log: {log})")
            return time.monotonic() - start, failed

        upstream = [t for t in todo if t.stages != (t.variant,)]
        variants = [t for t in todo if t.stages == (t.variant,)]
        lines = RunLines(len(todo), self.console, enabled=not self.quiet and not self.console.is_terminal)
        with children.forwarding_sigterm(), \
                Progress(TextColumn(f"[cyan]sweep[/] {self.sweep.name} ({jobs} jobs × {threads} threads)"),
                         BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("left"),
                         TimeRemainingColumn(), console=self.console, disable=self.quiet,
                         speed_estimate_period=7 * 24 * 3600) as progress:  # the pace of the whole sweep
            bar = progress.add_task("runs", total=len(todo))
            with ThreadPoolExecutor(max_workers=jobs) as pool:
                try:
                    for phase in (upstream, variants):  # the shared teachers first, so no job waits on another
                        futures = {pool.submit(one, task): task for task in phase}
                        for future in as_completed(futures):  # in the order they end
                            seconds, failed = future.result()
                            progress.advance(bar)
                            if not children.stopping:
                                lines.done(futures[future].title, seconds, failed)
                except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the runs stop after their step, checkpoints kept
                    children.stop()
                    raise
        return failures

    # -- collecting ----------------------------------------------------------------------------------------

    def records(self) -> tuple[list[RunRecord], list[str]]:
        """The finished runs (variants and their upstream stages) and the missing ones, grouped
        (:func:`~distilkit.sweep.tasks.missing_text`: variants missing the same seeds together)."""
        from distilkit.sweep.results import RunRecord

        records: list[RunRecord] = []
        missing: list[tuple[str, int]] = []
        seen: set[Path] = set()
        for seed in self.seeds:
            for variant in self.sweep.recipes:
                pipe = self.pipes[variant, seed]
                for name in [*self.sweep.upstream_stages(variant), variant]:
                    run_dir = pipe.run_dir(name)
                    summary = read_summary(run_dir)
                    if summary is None:
                        if name == variant:
                            missing.append((variant, seed))
                        continue
                    if run_dir in seen:  # a shared upstream run: counted once
                        continue
                    seen.add(run_dir)
                    upstream = name != variant
                    label = summary.get("label", name) if upstream else self.sweep.label(variant)
                    records.append(RunRecord(name, seed, run_dir, {**summary, "label": label}, upstream))
        return records, missing_text(missing, list(self.sweep.recipes))

    def order(self) -> list[str]:
        ups: list[str] = []
        for variant in self.sweep.recipes:
            ups += [n for n in self.sweep.upstream_stages(variant) if n not in ups]
        return [*self.sweep.recipes, *ups]

    @property
    def results_console(self) -> Any:
        """Where the sweep's table (and the runs left out of it) is printed: the console, or a loud one where it is
        quiet — quiet means no progress chatter, not no results."""
        if not getattr(self.console, "quiet", False):
            return self.console
        from distilkit.console import make_console

        return make_console()

    def collect(self, notes: list[str] | None = None) -> Path | None:
        """Print the table of the finished runs (even under ``quiet``) and write the results' files (``notes``: more
        lines for results.md, as ``--seeds auto`` says how it chose the seeds)."""
        records, missing = self.records()
        console = self.results_console
        if not records:
            console.print(f"sweep {self.sweep.name}: no finished runs yet under {self.root}")
            return None
        if missing:
            console.print(f"[yellow]not finished (left out of the table):[/] {'; '.join(missing)}", highlight=False)
        from distilkit.sweep.results import write_results

        return write_results(self.root, self.sweep.name, records, self.sweep.baseline, self.order(), console,
                             missing, notes or [])


def run_sweep(path: str | Path, output: str | Path = "runs", seeds: list[int] | None = None, jobs: int = 1,
              plan: bool = False, collect: bool = False, quiet: bool = False, launcher: str = "local",
              cluster: dict[str, Any] | None = None, status: bool = False, wait: bool = False,
              reuse: list[Path] | None = None) -> Path | None:
    """``distilkit sweep``: run (or plan, or only collect) a sweep file and write its results; with ``launcher``
    ``slurm``, queue its runs on Slurm (:mod:`distilkit.sweep.slurm`); ``status``: their states; ``wait``: until
    the queued runs have ended, then collect. ``plan`` runs, submits and waits for nothing, with either launcher.
    ``reuse``: folders whose finished runs of the same identity are copied in first (:mod:`distilkit.sweep.reuse`)."""
    if jobs < 1:
        raise DistilkitError(f"--jobs must be at least 1, got {jobs}")
    if plan and status:
        raise DistilkitError("--plan and --status: give one (--plan shows what would be run or submitted and asks "
                             "Slurm nothing; --status asks squeue about the jobs submitted)")
    sweep = SweepRun(path, output, seeds, quiet=quiet)
    if reuse:
        from distilkit.sweep.reuse import reuse_runs

        copied = reuse_runs(sweep, [Path(f) for f in reuse])
        print(f"--reuse: {len(copied)} finished run{'s' * (len(copied) != 1)} of the same configuration copied into "
              f"{sweep.root} from {', '.join(sorted({str(s.parent) for s, _ in copied})) or 'nowhere'}",
              file=sys.stderr)
    if plan:
        if wait:
            print("--wait: nothing is submitted with --plan, so nothing is waited for", file=sys.stderr)
        if launcher == "slurm":
            _slurm_plan(sweep, cluster or {})
        else:
            _local_plan(sweep, path, output)
        return None
    if status and launcher == "local" and not (sweep.root / "slurm" / "jobs.json").is_file():
        from distilkit.sweep.local_status import show

        show(sweep)  # a sweep run here: read from its folder
        return None
    if status or wait or launcher == "slurm":
        return _on_slurm(sweep, path, launcher, cluster or {}, status, wait, quiet)
    started = time.monotonic()
    failures = [] if collect else sweep.run(jobs)
    result = sweep.collect()
    if not quiet:
        sweep.console.print(f"sweep finished in {time.monotonic() - started:.1f} s")
    if failures:
        raise DistilkitError("some runs failed (the others are in the table):\n  " + "\n  ".join(failures))
    return result


def _local_plan(sweep: SweepRun, path: str | Path, output: str | Path) -> None:
    """``--plan``: one ``distilkit run`` command per run on stdout (upstream first), after writing the variants'
    recipes they run (``<output>/<sweep>/recipes``, named on stderr); nothing runs."""
    lines = sweep.plan()
    print(f"# {len(lines)} commands for sweep {sweep.sweep.name}: run the first {len(sweep.upstream_tasks())} (the "
          f"upstream stages) before the others; then `distilkit sweep {path} --output {output}` collects. The "
          f"recipes they run were written to {sweep.root / 'recipes'} (nothing else was written)", file=sys.stderr)
    print("\n".join(lines))


def _slurm_plan(sweep: SweepRun, cluster: dict[str, Any]) -> None:
    """``--plan --launcher slurm``: the jobs, their dependencies and sbatch scripts that a submission would queue,
    on stdout; no executor is built, no Slurm command runs and nothing is written."""
    from distilkit.sweep.slurm_plan import describe_plan, plan

    res = _resources(sweep, cluster)
    print(describe_plan(sweep, res, plan(sweep, res)))


def _resources(sweep: SweepRun, cluster: dict[str, Any]) -> Any:
    """One run's Slurm allocation: the command line's ``cluster`` values over the sweep file's ``launcher:``."""
    from distilkit.sweep.slurm import Resources, parse_slurm_options

    return Resources.merge(sweep.sweep.spec.launcher, {**cluster, "extra": parse_slurm_options(cluster.get("extra"))})


def _on_slurm(sweep: SweepRun, path: str | Path, launcher: str, cluster: dict[str, Any], status: bool, wait: bool,
              quiet: bool) -> Path | None:
    from distilkit.sweep import slurm, slurm_status

    console = sweep.console
    if status:
        for line in slurm_status.status(sweep):
            print(f"{line.state:8} {line.job_id:>12}  {line.title}  log {line.log}"
                  + (f"  — {line.detail}" if line.detail else ""))
        return None
    if launcher == "slurm":
        res = _resources(sweep, cluster)
        from distilkit.engine.train.trackers.base import in_sweep

        with in_sweep(sweep.sweep.name, list(sweep.sweep.recipes)):  # sbatch exports it to the jobs' trackers
            submitted = slurm.submit(sweep, res)
        total = len(sweep.variant_tasks())
        console.print(f"sweep [bold]{sweep.sweep.name}[/]: {len(submitted)} job(s) queued on Slurm for "
                      f"{total} runs ({res.cpus} CPUs, {res.gpus} GPUs, {res.time} min each); records in "
                      f"{sweep.root / 'slurm' / 'jobs.json'}", highlight=False)
        for item in submitted:
            after = f" after {', '.join(item.after)}" if item.after else ""
            print(f"  {item.job_id:>12}  {item.title}{after}  log {item.log}")
        if not wait:
            console.print(f"`distilkit sweep {path} --status` shows their states, `--wait` follows them, and "
                          f"`distilkit sweep {path}` collects the table once they have ended", highlight=False)
            return None
    states = slurm_status.wait(sweep, console, quiet=quiet)
    failed = [s for s in states if s.state == "failed"]
    result = sweep.collect()
    if failed:
        raise DistilkitError("some runs failed (the others are in the table):\n  " + "\n  ".join(
            f"{s.title}: job {s.job_id}, {s.detail} (log: {s.log})" for s in failed))
    return result


__all__ = ["SweepRun", "run_sweep"]
