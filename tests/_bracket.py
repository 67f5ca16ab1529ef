"""validate's memory estimate of a paper recipe's stage and the measured peak of one of its training steps: the
numbers test_paper_recipes' full-grid brackets compare, in the test's process (:func:`bracket`) or in one of their
own (``python tests/_bracket.py RECIPE STAGE SETS_JSON THREADS`` prints them as one JSON line)."""

from __future__ import annotations

import json
import sys


def bracket(path: str, stage: str, sets: list[str]) -> tuple[str, float, float, float]:
    """(how the estimate was made, its low bound, the measured peak, its high bound), in bytes."""
    from distilkit.data.probe import _one_scene
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.engine.memory.estimate import estimate_stage, measure_step
    from distilkit.recipe import load_recipe, parse_overrides

    res = resolve(load_recipe(path, parse_overrides(sets)), path)
    estimate = estimate_stage(res, stage)
    peak = measure_step(res, stage, _one_scene(res.data_params)).total
    if estimate is None:
        return "none", 0.0, peak, 0.0
    return estimate.how, estimate.low, peak, estimate.high


if __name__ == "__main__":
    import torch

    torch.set_num_threads(int(sys.argv[4]))
    print(json.dumps(bracket(sys.argv[1], sys.argv[2], json.loads(sys.argv[3]))))
