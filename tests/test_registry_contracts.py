"""Every registered adapter, objective, task loss, metric and dataset keeps its contract.

Parametrised over the registries at collection time (built-ins and installed plugins), so a new
component is checked without a new test. Adapters run one real batch of data that provides their
inputs and must return every declared tap with the declared kind.
"""

from __future__ import annotations

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import TINY_DATA
from distilkit.data.datasets import build_synthetic, collate_street, synthetic_info
from distilkit.data.params import SyntheticParams
from distilkit.metrics.base import Metric
from distilkit.registry import ADAPTERS, DATASETS, METRICS, OBJECTIVES, TASK_LOSSES
from distilkit.taps import DENSE_GRID_KINDS, TAP_KINDS, check_tap
from distilkit.term import Term

BUILTIN = {"adapters": ["scpnet", "js3cnet", "voxformer-proposal", "voxformer"], "metrics": ["ssc", "occupancy"]}
CAMERA = {"height": 24, "width": 80, "previous": [3]}


def names(registry) -> list[str]:
    return [e.name for e in registry]


@pytest.mark.parametrize("name", names(ADAPTERS))
def test_adapter_contract(name: str) -> None:
    cls = ADAPTERS.get(name)
    assert isinstance(cls.VERSION, int) and cls.VERSION >= 1
    assert cls.PREDICTION_TAP in cls.TAPS, "the prediction tap must be declared"
    assert set(cls.TAPS.values()) <= set(TAP_KINDS), "every tap kind is registered"
    data = SyntheticParams(**TINY_DATA, camera=CAMERA)  # the streets with their camera: LiDAR and camera fields
    info = synthetic_info(data)
    params = cls.Params()
    if "frames" in type(params).model_fields:
        params = params.model_copy(update={"frames": 2})
    reads = cls.inputs(params)
    for loss in cls.DEFAULT_TASK_LOSSES:
        task = TASK_LOSSES.get(loss["name"])
        assert set(task.CONSUMES.values()) <= set(cls.TAPS.values()), f"default task loss {loss['name']} fits"
        if reads <= info.fields:
            assert {task.default_field(role, info.fields) for role in task.BATCH} <= info.fields
    if not reads <= info.fields:
        return  # adapters on other data (or inputs from another stage) are run by the tests that define them
    assert cls.check_data(params, info) == []
    assert isinstance(cls.describe(params), str)
    torch.manual_seed(0)
    model = cls(params, info).eval()
    ds = build_synthetic(data, "train")
    with torch.no_grad():
        out = model(collate_street([ds[0], ds[1]]))
    for tap, kind in cls.TAPS.items():
        check_tap(out[tap], kind, f"{name}.{tap}")
        grid = cls.tap_grid(tap, params, info)
        if kind == "sparse_features" and grid is not None:
            # the value carries the geometry the adapter declares (validate's alignments use the declaration)
            assert out[tap].grid == grid, f"{name}.{tap} carries its declared grid"
        if kind in DENSE_GRID_KINDS:  # a dense volume's grid is declared (validate and init align with it) and true
            assert grid is not None and tuple(out[tap].shape[2:]) == tuple(grid.shape), f"{name}.{tap} on its grid"
    assert set(ADAPTERS.entry(name).consumes) <= set(cls.TAPS.values())


@pytest.mark.parametrize("name", names(ADAPTERS))
def test_adapter_aux_inputs_and_data_params_are_real(name: str) -> None:
    """``AUX_INPUTS`` names inputs the adapter reads that no dataset gives, each from a registered adapter's
    prediction; ``DATA_PARAMS`` are parameters of the synthetic data that serve the adapter (``distilkit init``
    writes both)."""
    from distilkit.schema_doc import aux_only_inputs

    cls = ADAPTERS.get(name)
    reads = cls.INPUTS | cls.inputs(cls.Params())
    for field, adapter in cls.AUX_INPUTS.items():
        assert field in reads and field in aux_only_inputs(frozenset({field})), (name, field)
        assert adapter in ADAPTERS.names(), (name, adapter)
    if cls.DATA_PARAMS:
        info = synthetic_info(SyntheticParams(**TINY_DATA, **cls.DATA_PARAMS))
        assert cls.check_data(cls.Params(), info) == [], name
        assert cls.check_data(cls.Params(), synthetic_info(SyntheticParams(**TINY_DATA))) != [], name


TERMS = [("objective", n) for n in names(OBJECTIVES)] + [("task loss", n) for n in names(TASK_LOSSES)]


@pytest.mark.parametrize(("what", "name"), TERMS)
def test_term_contract(what: str, name: str) -> None:
    """Task losses and objectives share one protocol: roles with declared sources, one lifecycle."""
    entry = (OBJECTIVES if what == "objective" else TASK_LOSSES).entry(name)
    cls = entry.obj
    assert issubclass(cls, Term)
    mod = cls(cls.Params())  # every parameter has a default: `{name: X}` alone is a valid recipe line
    assert isinstance(mod, torch.nn.Module)
    assert "student" in cls.CONSUMES and cls.TEACHER_ROLES <= set(cls.CONSUMES), "roles and their sources"
    assert not set(cls.CONSUMES) & set(cls.BATCH), "a role has one source"
    assert set(cls.roles()) == set(cls.CONSUMES) | set(cls.BATCH)
    assert set(cls.CONSUMES.values()) <= set(TAP_KINDS)
    assert cls.OPTIONAL <= set(cls.CONSUMES) and "student" not in cls.OPTIONAL
    assert all(isinstance(c, str) and c.isidentifier() for c in cls.REQUIRES), "teacher capabilities are methods"
    assert cls.DEFAULT_WEIGHT > 0 and isinstance(cls.VERSION, int) and cls.VERSION >= 1
    assert set(entry.consumes) == set(cls.CONSUMES.values())
    if what == "objective":  # an objective reads a teacher tap, calls a teacher capability or compares to the data
        assert cls.TEACHER_ROLES or cls.REQUIRES or cls.BATCH
        assert entry.paper and entry.meta.get("equation") and entry.meta.get("shapes"), "documented in objectives.md"
    else:
        assert not cls.TEACHER_ROLES and not cls.REQUIRES, "a task loss reads no teacher"


@pytest.mark.parametrize("name", names(METRICS))
def test_metric_contract(name: str) -> None:
    cls = METRICS.get(name)
    assert issubclass(cls, Metric)
    assert cls.SCORES in TAP_KINDS and cls.KEYS and cls.LOWER_IS_BETTER <= set(cls.KEYS)
    assert METRICS.entry(name).consumes == (cls.SCORES,)


@pytest.mark.parametrize("name", names(DATASETS))
def test_dataset_contract(name: str) -> None:
    entry = DATASETS.entry(name)
    assert callable(entry.obj) and callable(entry.meta["collate"]) and callable(entry.meta["info"])
    assert isinstance(entry.meta["version"], int) and entry.meta["params"] is not None


def test_the_builtins_are_registered() -> None:
    assert set(BUILTIN["adapters"]) <= set(names(ADAPTERS)) and set(BUILTIN["metrics"]) <= set(names(METRICS))
    assert len(names(OBJECTIVES)) >= 10


def test_an_alias_names_the_same_component_and_a_deprecated_one_warns_without_changing_identities(tmp_path) -> None:
    """Names are part of stage identities: a renamed component keeps the old name as a deprecated alias, and a
    recipe using it resolves and hashes as the new name (timm's practice)."""
    import warnings

    import pytest

    from conftest import tiny_recipe
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict
    from distilkit.registry import OBJECTIVES

    OBJECTIVES.alias("dense_to_sparse", "dskd", deprecated=True)
    OBJECTIVES.alias("scpnet_relational", "dskd")
    try:
        plain = Pipeline(recipe_from_dict(tiny_recipe()), tmp_path, quiet=True)
        with pytest.warns(FutureWarning, match="objective 'dense_to_sparse' is deprecated: use 'dskd'"):
            old = tiny_recipe()
            old["stages"]["student"]["distill"][0]["name"] = "dense_to_sparse"
            renamed = Pipeline(recipe_from_dict(old), tmp_path, quiet=True)
        assert renamed.hashes == plain.hashes and renamed.resolved.stages["student"].distill[0].key == "dskd"
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a plain alias does not warn
            other = tiny_recipe()
            other["stages"]["student"]["distill"][0]["name"] = "scpnet_relational"
            assert Pipeline(recipe_from_dict(other), tmp_path, quiet=True).hashes == plain.hashes
        assert "scpnet_relational" in OBJECTIVES and "scpnet_relational" not in OBJECTIVES.names()
        assert OBJECTIVES.aliases_of("dskd") == ["dense_to_sparse", "scpnet_relational"]
        with pytest.raises(ValueError, match="registered itself"):
            OBJECTIVES.alias("kd", "dskd")
    finally:
        OBJECTIVES.remove("dense_to_sparse")
        OBJECTIVES.remove("scpnet_relational")
    assert OBJECTIVES.aliases_of("dskd") == []
