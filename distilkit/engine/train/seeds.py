"""A recipe over several training seeds (``distilkit run --seed 0 1 2``): each seed its own run, then one table of
mean ± std and paired differences (:mod:`distilkit.report.seeds`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from distilkit.errors import DistilkitError
from distilkit.report.seeds import default_baseline, seed_rows, write_seeds_report


def run_seeds(recipe: str | Path, output: str | Path, seeds: list[int], baseline: str | None = None,
              quiet: bool = False, rerun: list[str] | None = None, only: list[str] | None = None,
              wait: bool = True, overrides: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Run the recipe once per seed (finished stages are reused), then report mean ± std over the seeds."""
    from distilkit.engine.train.pipeline import Pipeline

    if len(set(seeds)) != len(seeds):
        raise DistilkitError(f"--seed: give each seed once, got {' '.join(map(str, seeds))}")
    results: dict[int, list[Any]] = {}
    pipe = None
    for seed in seeds:
        pipe = Pipeline(recipe, output, quiet=quiet, seed=seed, overrides=overrides)
        if baseline is not None:
            pipe.check_stages("--baseline", [baseline])
        if not quiet:
            pipe.console.rule(f"seed {seed}")
        results[seed] = pipe.run(rerun=rerun, only=only, wait=wait)
    assert pipe is not None
    chosen = baseline if baseline is not None else default_baseline(pipe.resolved)
    rows = seed_rows(results, chosen, pipe.resolved.recipe.report.compare)
    if pipe.world.main:  # multi-process runs: one writer
        write_seeds_report(pipe.root, rows, chosen, pipe.console)
    return rows


__all__ = ["run_seeds"]
