"""``distilkit validate RECIPE ...``: a recipe checked without training — names, parameters, taps, the data and the
weights files it reads, whether its sparse convolutions can run where each stage runs, and each training stage's
first step on a dry batch (every term on the shapes its taps will have) — and each training stage's memory per step
estimated."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from distilkit.cli.base import command, overrides, set_option, threads_option

EXAMPLES = {
    "validate": ["distilkit validate recipes/quickstart.yaml",
                 "distilkit validate recipes/semantickitti_scpnet.yaml --set data.params.root=/data/semantickitti"],
}


def add(sub: Any) -> None:
    v = command(sub, "validate", "check recipes without training (exit status 2 on a problem)", EXAMPLES["validate"])
    v.add_argument("recipes", nargs="+", help="recipe YAML files")
    set_option(v, "override recipe fields by dotted path, e.g. --set stages.student.train.steps=10")
    threads_option(v)
    v.add_argument("--no-memory", action="store_true", help="skip the memory estimate (two training steps of each "
                   "stage at a small size); each stage's terms still run once on a small dry batch")
    v.add_argument("--static", action="store_true", help="run no model at all: neither the memory estimate nor the "
                   "terms on a dry batch (quick for large networks on a CPU; an error a term raises at its first "
                   "step is then not found)")
    v.set_defaults(fn=validate)


def validate(args: argparse.Namespace) -> int:
    from distilkit.engine.assemble.checks import data_notes, describe, run_problems
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.errors import RecipeError
    from distilkit.recipe import load_recipe

    for path in args.recipes:
        res = resolve(load_recipe(path, overrides(args)), str(path))
        unreadable, problems = run_problems(res)  # what the run needs: its data, weights files, sparse backend
        if problems:
            if unreadable and not (args.no_memory or args.static):
                print("memory not estimated: the data cannot be read", file=sys.stderr)
            raise RecipeError(problems, str(path))
        lines, problems = (["terms not run on a dry batch (--static): a term's error at its first step is not "
                            "checked"], []) if args.static else _first_steps(res, memory=not args.no_memory)
        if problems:
            raise RecipeError(problems, str(path))
        stages, networks = describe(res)
        print(f"{path}: ok — {len(res.stages)} stage(s): {stages}")
        for line in networks:
            print(f"  {line}")
        print(f"  {_threads_line(res.recipe.threads)}")
        for note in data_notes(res):
            print(f"  note: {note}")
        _report(res, lines)
    return 0


def _threads_line(requested: int | None) -> str:
    """The CPU threads each process will compute with, and where the figure comes from."""
    from distilkit.engine.train.cpus import run_threads, usable_cpus

    threads, source = run_threads(requested)
    why = "the recipe's threads or --threads" if source == "threads" else source
    line = f"threads: {threads} per process ({why}; {usable_cpus()} CPUs usable)"
    if source not in ("threads", "OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK") and threads > 1:
        line += "; on a machine shared with other busy processes give --threads (fewer threads than cores)"
    return line


def _first_steps(res: Any, memory: bool) -> tuple[list[Any], list[tuple[str, str]]]:
    """Each training stage's first step on a dry batch — with ``memory``, the estimate's two steps at each probe
    size (:func:`~distilkit.engine.memory.estimate.estimate_stage`), else its terms once on the smallest
    (:func:`~distilkit.engine.memory.probe.check_terms`): (per stage in order, its estimate or a note saying why
    there is none; the problems: each stage whose step fails as the run's would)."""
    from distilkit.console import make_console
    from distilkit.engine.memory.probe import StepFailure, check_terms
    from distilkit.engine.train.oom import is_out_of_memory

    console = make_console()
    lines: list[Any] = []
    problems: list[tuple[str, str]] = []
    what = "two training steps at a small size, to run its terms and estimate its memory" if memory else \
        "its terms on a dry batch"
    for name in res.order:
        if res.stages[name].spec.train.steps == 0:  # evaluates only: no step, no terms
            continue
        try:
            with console.status(f"stage {name}: {what}"):
                estimate = _estimate(res, name) if memory else None
                if isinstance(estimate, str):
                    lines.append(estimate)
                elif estimate is not None:
                    lines.append(estimate)
                    continue
                check_terms(res, name)  # none asked for, none possible (no probe plan), or none made: the terms
        except StepFailure as exc:  # the run's own first step would fail the same way
            problems.append((exc.field, exc.problem))
        except Exception as exc:
            if not is_out_of_memory(exc):
                raise
            lines.append(f"stage {name}: its terms did not run: a training step ran out of memory on one sample, "
                         "so it will not fit at the recipe's size either (lower train.batch_size or the grid)")
    return lines, problems


def _estimate(res: Any, name: str) -> Any:
    """Stage ``name``'s memory estimate; None where its dataset has no probe plan; a note (str) where the
    measurement, not the stage's step, failed. A step that fails as the run's would raises
    :class:`~distilkit.engine.memory.probe.StepFailure`; running out of memory passes through."""
    from distilkit.engine.memory.estimate import estimate_stage
    from distilkit.engine.memory.probe import StepFailure
    from distilkit.engine.train.oom import is_out_of_memory

    try:
        return estimate_stage(res, name)
    except StepFailure:
        raise
    except Exception as exc:
        if is_out_of_memory(exc):
            raise
        return f"stage {name}: memory not estimated (the measurement failed: {type(exc).__name__}: {exc})"


def _report(res: Any, lines: list[Any]) -> None:
    """Each training stage's memory per step (two steps at small sizes, scaled), with a warning where it does not
    fit in what the machine has free, or the note saying why it has none."""
    from distilkit.console import make_console

    console = make_console()
    for estimate in lines:
        if isinstance(estimate, str):
            console.print(f"[yellow]{estimate}[/]", highlight=False, soft_wrap=True)
            continue
        print(f"  {estimate.line()}")
        warning = estimate.warning()
        if warning:
            stage = res.stages[estimate.stage]
            console.print(f"[yellow]warning:[/] {warning}: lower train.batch_size (now {estimate.batch_size}), the "
                          f"grid (data.params.scale) or the size of {stage.student.adapter}'s model", highlight=False,
                          soft_wrap=True)
