"""Property-based tests (hypothesis): random mutations of valid recipes and sweep files. Only RecipeError
escapes the loaders (the CLI: exit status 2, one message); a short run of a mutated recipe ends in success or a
DistilkitError (exit status 2), never in another exception."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import tiny_recipe
from distilkit.cli import main
from distilkit.engine.assemble.resolve import resolve
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.sweep.spec import SweepSpec, load_sweep

NAMES = ["scpnet", "js3cnet", "lidiff", "dskd", "kd", "fitnets", "ce", "lovasz", "teacher", "student", "miou",
         "synthetic-lidar", "completion", "feature", "logits", "best", "last", "linear", "adam", "sgd", "bf16"]

# values a mutation puts in: wrong types, out-of-range numbers, near-miss names, containers
SMALL_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-3, 64), st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from(NAMES), st.text(max_size=8),
    st.lists(st.integers(-2, 16), max_size=3), st.dictionaries(st.sampled_from(NAMES), st.integers(0, 4), max_size=2))


def paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path to a value in nested dicts and lists."""
    out = [prefix] if prefix else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += paths(v, prefix + (i,))
    return out


@st.composite
def mutated(draw: Any, valid: dict[str, Any], values: Any = SMALL_VALUES, under: tuple = ()) -> dict[str, Any]:
    """``valid`` with one to three mutations: a value replaced, a key deleted, an unknown key added, a key renamed."""
    data = copy.deepcopy(valid)
    for _ in range(draw(st.integers(1, 3))):
        candidates = [p for p in paths(data) if p[: len(under)] == under and len(p) > len(under)]
        if not candidates:
            break
        path = draw(st.sampled_from(candidates))
        parent: Any = data
        for part in path[:-1]:
            parent = parent[part]
        key = path[-1]
        kind = draw(st.sampled_from(["replace", "replace", "delete", "add", "rename"]))
        if kind == "replace":
            parent[key] = draw(values)
        elif kind == "delete":
            del parent[key]
        elif kind == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(NAMES + ["extra"]))] = draw(values)
        elif kind == "rename" and isinstance(parent, dict):
            parent[draw(st.sampled_from(NAMES)) + "_"] = parent.pop(key)
    return data


RECIPE = tiny_recipe(steps=1)
SWEEP = {"schema_version": 1, "name": "sw", "recipe": copy.deepcopy(RECIPE), "stage": "student", "seeds": [0, 1],
         "variants": {"none": {"distill": []}, "kd": {"distill": [{"name": "kd", "weight": 1.0}]},
                      "lr": {"set": {"stages.student.optimizer.lr": 0.01}}}}
# derandomize: the same examples on every run (seeded from the test's name), so CI is repeatable; after changing the
# loaders, search wider once by hand (derandomize=False, more examples)
PROPERTY = settings(max_examples=250, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])


def dump(data: Any) -> str:
    """``yaml.safe_dump`` by libyaml's emitter where PyYAML has it (the same safe representer, a fifth of the time;
    the loaders under test read the files as they read any)."""
    return yaml.dump(data, Dumper=getattr(yaml, "CSafeDumper", yaml.SafeDumper))


def load_and_resolve(data: Any) -> None:
    resolve(recipe_from_dict(data, "mutated"), "mutated")


def test_the_valid_originals_load() -> None:
    assert list(resolve(recipe_from_dict(RECIPE, "valid"), "valid").stages) == ["teacher", "student"]
    assert list(SweepSpec.model_validate(SWEEP).variants) == ["none", "kd", "lr"]


@PROPERTY
@given(mutated(RECIPE))
def test_mutated_recipes_raise_only_recipe_errors(data: dict[str, Any]) -> None:
    try:
        load_and_resolve(data)
    except RecipeError as err:
        assert str(err).startswith("mutated:") and len(str(err)) < 4000
    # anything else (KeyError, TypeError, ValidationError, ...) fails the test


@PROPERTY
@given(mutated(SWEEP))
def test_mutated_sweep_files_raise_only_recipe_errors(tmp_path_factory: pytest.TempPathFactory,
                                                      data: dict[str, Any]) -> None:
    from distilkit.sweep.runner import SweepRun

    path = tmp_path_factory.mktemp("sweep") / "sweep.yaml"
    path.write_text(dump(data))
    try:
        SweepRun(load_sweep(path), tmp_path_factory.mktemp("runs"), quiet=True)
    except RecipeError as err:
        assert str(err).startswith(str(path))


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(mutated(RECIPE), st.one_of(st.none(), st.floats(0.0, 1.0)))
def test_the_cli_answers_mutated_recipes_with_status_0_or_2(tmp_path: Path, capsys: Any, data: Any,
                                                            cut: float | None) -> None:
    path = tmp_path / "r.yaml"
    text = dump(data)
    if cut is not None:  # a file cut at a random place, as a crash or a bad copy leaves it
        text = text[: int(len(text) * cut)]
    path.write_text(text)
    status = main(["validate", str(path), "--no-memory"])  # the short runs below train mutated recipes
    err = capsys.readouterr().err
    assert status in (0, 2)
    if status == 2:
        assert err.startswith("error: ") and "Traceback" not in err


def _limited() -> None:  # in the child: 4 GiB of address space, so a runaway allocation fails there, not CI
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))


def _short_runs(tmp_path: Path, recipes: list[Any]) -> None:
    """One training step (--stop-after 1) of each mutated recipe, all in one process of their own with a memory
    limit (tests/_short_runs.py: `distilkit run` in-process, one interpreter start for all): each ends in success,
    or exit status 2 with one "error:" line — never a traceback."""
    import json
    import subprocess
    import sys

    assert recipes
    paths = []
    for i, data in enumerate(recipes):
        paths.append(path := tmp_path / f"r{i}.yaml")
        path.write_text(dump(data))
    done = subprocess.run([sys.executable, str(Path(__file__).parent / "_short_runs.py"), str(tmp_path),
                           *map(str, paths)], capture_output=True, text=True, preexec_fn=_limited, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    results = json.loads((tmp_path / "results.json").read_text())
    assert [r["recipe"] for r in results] == list(map(str, paths))
    for data, r in zip(recipes, results):
        assert r["status"] in (0, 2), f"{yaml.safe_dump(data)}\n{r['stderr'][-2000:]}"
        if r["status"] == 2:
            assert r["stderr"].startswith("error: ") and "Traceback" not in r["stderr"], r["stderr"][-2000:]


SHORT_RUNS = dict(deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow])


def _drawn(n: int) -> list[Any]:
    """``n`` mutations of the recipe's stages (the data stays small), drawn by hypothesis (derandomized)."""
    drawn: list[Any] = []

    @settings(max_examples=n, **SHORT_RUNS)
    @given(mutated(RECIPE, under=("stages",)))
    def draw(data: Any) -> None:
        drawn.append(data)

    draw()
    return drawn


def test_short_runs_of_mutated_recipes_end_in_success_or_a_clear_error(tmp_path: Path) -> None:
    """Mutations of the stages only (the data stays small): a few here, twenty in the slow run below."""
    _short_runs(tmp_path, _drawn(4))


@pytest.mark.slow
def test_twenty_short_runs_of_mutated_recipes_end_in_success_or_a_clear_error(tmp_path: Path) -> None:
    _short_runs(tmp_path, _drawn(20))
