"""The threads a run computes with (issue 57, item 16): ``--threads``, the recipe's ``threads``, ``OMP_NUM_THREADS``,
Slurm's ``SLURM_CPUS_PER_TASK``, the affinity mask — in that order — recorded in each stage's summary, and not part
of any stage's identity."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import tiny_recipe
from distilkit.engine.train.cpus import default_threads, run_threads, usable_cpus


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    for name in ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK"):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_the_default_is_omp_then_slurm_then_the_affinity_mask(clean_env: pytest.MonkeyPatch) -> None:
    cpus = usable_cpus()
    assert default_threads() == (cpus, "the CPUs this process may use")
    clean_env.setenv("SLURM_CPUS_PER_TASK", "1")
    assert default_threads() == (1, "SLURM_CPUS_PER_TASK")
    clean_env.setenv("OMP_NUM_THREADS", "1,1")  # OMP's nested form: the first level
    assert default_threads() == (1, "OMP_NUM_THREADS")
    clean_env.setenv("OMP_NUM_THREADS", str(cpus + 7))  # as given, as OpenMP takes it (a test pins 2 on 1 CPU)
    assert default_threads() == (cpus + 7, "OMP_NUM_THREADS")
    clean_env.setenv("OMP_NUM_THREADS", "zero")  # not a count: the next source
    assert default_threads() == (1, "SLURM_CPUS_PER_TASK")
    assert run_threads(3) == (3, "threads")  # the recipe's or the command line's, as given


def test_the_recipe_refuses_a_thread_count_below_one() -> None:
    from distilkit.errors import RecipeError
    from distilkit.recipe import recipe_from_dict

    with pytest.raises((RecipeError, ValueError), match="threads"):
        recipe_from_dict({**tiny_recipe(steps=1), "threads": 0})


def test_threads_are_not_part_of_a_stage_identity() -> None:
    from distilkit.engine.train.context import RecipeRun
    from distilkit.recipe import recipe_from_dict

    plain = RecipeRun(recipe_from_dict(tiny_recipe(steps=1)), quiet=True)
    two = RecipeRun(recipe_from_dict({**tiny_recipe(steps=1), "threads": 2}), quiet=True)
    assert plain.hashes == two.hashes


def _run(tmp_path: Path, env: dict[str, str], *args: str) -> dict:
    tmp_path.mkdir(parents=True, exist_ok=True)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(tiny_recipe(steps=1)), encoding="utf-8")
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK")}
    out = subprocess.run([sys.executable, "-m", "distilkit", "run", str(recipe), "-o", str(tmp_path / "runs"), "-q",
                          "--stage", "teacher", *args], env={**base, **env}, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    summary = next((tmp_path / "runs").glob("*/teacher-*/summary.json"))
    return json.loads(summary.read_text(encoding="utf-8"))


def test_a_run_computes_with_slurms_cpus_and_the_command_line_wins(tmp_path: Path) -> None:
    """PyTorch's own default ignores ``SLURM_CPUS_PER_TASK`` (every core of the node without a cpuset); a stage's
    summary records the count it ran with."""
    slurm = _run(tmp_path / "a", {"SLURM_CPUS_PER_TASK": "1"})
    assert slurm["threads"] == 1
    forced = _run(tmp_path / "b", {"SLURM_CPUS_PER_TASK": "1"}, "--threads", "2")
    assert forced["threads"] == 2


def test_validate_says_the_threads_and_where_they_come_from(tmp_path: Path, clean_env: pytest.MonkeyPatch,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from distilkit.cli import main

    recipe = tmp_path / "r.yaml"
    recipe.write_text(yaml.safe_dump(tiny_recipe(steps=1)), encoding="utf-8")
    clean_env.setenv("SLURM_CPUS_PER_TASK", "1")
    assert main(["validate", str(recipe), "--static"]) == 0
    assert "threads: 1 per process (SLURM_CPUS_PER_TASK" in capsys.readouterr().out
    assert main(["validate", str(recipe), "--static", "--threads", "3"]) == 0
    assert "threads: 3 per process (the recipe's threads or --threads" in capsys.readouterr().out
