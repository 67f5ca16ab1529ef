"""One finished run of conftest's tiny recipe at a step a stage (``tiny_recipe(steps=1)``: a teacher and its DSKD
student) per test process, read by tests/test_pipeline.py and tests/test_new_user.py; their tests that read it are in
one xdist_group ("tiny_runs"), so that one worker trains it once. Read only: a test that changes it works on a copy."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from conftest import tiny_recipe

_RUNS: dict[str, tuple[Path, list[Any]]] = {}


def tiny_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Any]]:
    """(the folder whose ``runs/`` holds the run, the pipeline's results: teacher, student), trained on this
    process's first call."""
    key = str(tmp_path_factory.getbasetemp())
    if key not in _RUNS:
        from distilkit.engine.train.pipeline import Pipeline
        from distilkit.recipe import recipe_from_dict

        root = tmp_path_factory.mktemp("tiny_runs")
        results = Pipeline(recipe_from_dict(tiny_recipe(steps=1)), root / "runs", quiet=True).run()
        assert [r.reused for r in results] == [False, False]
        _RUNS[key] = (root, results)
    return _RUNS[key]
