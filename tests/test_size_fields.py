"""A field that only one ``size`` of an adapter reads, given with the other size, is an error naming it (it would be
ignored without a word: e.g. ``channels`` with SCPNet's ``size: paper``, whose widths are the release's)."""

from __future__ import annotations

import pytest
from pydantic import BaseModel, ValidationError

from conftest import ROOT
from distilkit.cli import main
from distilkit_adapters.dean.adapter import DeanParams
from distilkit_adapters.js3cnet.adapter import JS3CNetParams
from distilkit_adapters.lidiff.adapter import LiDiffParams
from distilkit_adapters.lidiff.refine import RefineParams
from distilkit_adapters.scpnet.adapter import SCPNetParams

# (params, a field of one size, a value, the size that reads it, the other size)
CASES = [(SCPNetParams, "channels", 16, "tiny", "paper"), (SCPNetParams, "seg_channels", 16, "tiny", "paper"),
         (SCPNetParams, "point_mlp", [8], "tiny", "paper"), (SCPNetParams, "semantics", "spconv2", "paper", "tiny"),
         (JS3CNetParams, "embed", 8, "tiny", "paper"), (JS3CNetParams, "levels", 3, "paper", "tiny"),
         (DeanParams, "channels", 8, "tiny", "paper"), (DeanParams, "semantics", "spconv2", "paper", "tiny"),
         (LiDiffParams, "channels", 8, "tiny", "paper"), (RefineParams, "k", 3, "tiny", "paper")]


@pytest.mark.parametrize("cls, field, value, reads, other", CASES,
                         ids=[f"{c.__name__}.{f}" for c, f, *_ in CASES])
def test_a_field_of_the_other_size_is_named(cls: type[BaseModel], field: str, value: object, reads: str,
                                           other: str) -> None:
    assert getattr(cls(size=reads, **{field: value}), field) == value  # read by its own size
    with pytest.raises(ValidationError) as err:
        cls(size=other, **{field: value})
    assert f"{field} is read by size {reads} only; size {other} does not use it" in str(err.value)
    cls(size=other)  # the defaults of the fields neither size was given stay valid
    cls.model_validate(cls(size=other).model_dump())  # and every default written out (a checkpoint's parameters)


def test_validate_names_the_stage_and_the_field(capsys) -> None:
    recipe = ROOT / "recipes" / "paper" / "scpnet.yaml"
    assert main(["validate", "--static", str(recipe), "--set", "stages.student.model.params.channels=16"]) == 2
    err = capsys.readouterr().err
    assert "stages.student.model.params: channels is read by size tiny only; size paper does not use it" in err
