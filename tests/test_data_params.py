"""The data parameters' checks, as `distilkit validate` reports them."""

from __future__ import annotations

from pathlib import Path

import yaml

from conftest import tiny_recipe
from distilkit.cli import main


def test_a_scale_that_does_not_divide_the_grid_is_named_with_the_ones_that_do(tmp_path: Path, capsys) -> None:
    recipe = tiny_recipe()
    recipe["data"]["params"]["scale"] = 3
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", "--static", str(path)]) == 2
    said = capsys.readouterr()
    assert "scale must be one of (1, 2, 4, 8) (256x256x32 divided by it), got 3" in said.out + said.err
