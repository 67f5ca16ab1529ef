"""``distilkit validate RECIPE ...``: a recipe checked without training — names, parameters, taps, the data and the
weights files it reads — and each training stage's memory per step estimated."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from distilkit.cli.base import command, overrides, set_option

EXAMPLES = {
    "validate": ["distilkit validate recipes/quickstart.yaml",
                 "distilkit validate recipes/semantickitti_scpnet.yaml --set data.params.root=/data/semantickitti"],
}


def add(sub: Any) -> None:
    v = command(sub, "validate", "check recipes without training (exit status 2 on a problem)", EXAMPLES["validate"])
    v.add_argument("recipes", nargs="+", help="recipe YAML files")
    set_option(v, "override recipe fields by dotted path, e.g. --set stages.student.train.steps=10")
    v.add_argument("--no-memory", action="store_true", help="skip the memory estimate (two training steps of each "
                   "stage at a small size)")
    v.set_defaults(fn=validate)


def validate(args: argparse.Namespace) -> int:
    from distilkit.engine.assemble.checks import describe, run_problems
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.errors import RecipeError
    from distilkit.recipe import load_recipe

    for path in args.recipes:
        res = resolve(load_recipe(path, overrides(args)), str(path))
        unreadable, problems = run_problems(res)  # what the run needs: its data and its weights files
        if problems:
            if unreadable and not args.no_memory:
                print("memory not estimated: the data cannot be read", file=sys.stderr)
            raise RecipeError(problems, str(path))
        stages, networks = describe(res)
        print(f"{path}: ok — {len(res.stages)} stage(s): {stages}")
        for line in networks:
            print(f"  {line}")
        if not args.no_memory:
            _memory(res)
    return 0


def _memory(res: Any) -> None:
    """Each training stage's memory per step (two steps at small sizes, scaled), with a warning where it does not
    fit in what the machine has free."""
    from distilkit.console import make_console
    from distilkit.engine.memory.estimate import estimate_stage

    console = make_console()
    for name in res.order:
        try:
            with console.status(f"stage {name}: two training steps at a small size, to estimate its memory"):
                estimate = estimate_stage(res, name)
        except Exception as exc:  # the estimate is advice: a probe that fails must not fail validation
            console.print(f"[yellow]stage {name}: memory not estimated ({type(exc).__name__}: {exc})[/]")
            continue
        if estimate is None:
            continue
        print(f"  {estimate.line()}")
        warning = estimate.warning()
        if warning:
            stage = res.stages[name]
            console.print(f"[yellow]warning:[/] {warning}: lower train.batch_size (now {estimate.batch_size}), the "
                          f"grid (data.params.scale) or the size of {stage.student.adapter}'s model", highlight=False,
                          soft_wrap=True)
