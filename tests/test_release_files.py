"""Released weights files that cannot be what they claim (issue 44, item 5): a file holding Python objects beyond
plain weights names each one (module.qualname), a truncated or empty file says it is not a complete PyTorch file and
its size, BatchNorm statistics no trained model has (a negative running variance, NaN) are refused with the key
named as the model calls it and as the release spells it — by the importers, by ``validate`` and by a run."""

from __future__ import annotations

import argparse
import os
import warnings
from pathlib import Path

import pytest
import torch
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import make_trainer, tiny_recipe
from distilkit.cli import main
from distilkit.errors import DataError


class RunConfig:
    """A training script's own class, pickled beside the weights."""

    class Optim:
        pass


def weights() -> dict[str, torch.Tensor]:
    return {"seg_head.0.weight": torch.ones(4), "seg_head.0.bias": torch.zeros(4),
            "seg_head.0.running_mean": torch.zeros(4), "seg_head.0.running_var": torch.ones(4),
            "seg_head.0.num_batches_tracked": torch.tensor(7)}


def read(path: Path):
    from distilkit_adapters.js3cnet.adapter import JS3CNetAdapter

    return JS3CNetAdapter.read_weights(str(path))  # a release importer: the bare state dict, under the model's names


@pytest.mark.parametrize("extra, named", [
    ({"args": argparse.Namespace(lr=0.1)}, "argparse.Namespace"),
    ({"config": RunConfig()}, f"{__name__}.RunConfig"),
    ({"optim": RunConfig.Optim()}, f"{__name__}.RunConfig.Optim"),  # protocol 2 spells it getattr(RunConfig, ...)
    ({"cmd": os.system}, f"{os.system.__module__}.system"),
])
@pytest.mark.parametrize("protocol", [2, 4])
def test_a_file_holding_more_than_weights_names_what_it_holds(tmp_path, extra, named, protocol) -> None:
    path = tmp_path / "release.pth"
    torch.save({"state_dict": weights(), **extra}, path, pickle_protocol=protocol)
    with warnings.catch_warnings(), pytest.raises(DataError) as err:
        warnings.filterwarnings("ignore", "Detected pickle protocol")  # torch's, for protocol 4
        read(path)
    text = str(err.value)
    assert f"it holds {named}," in text and "never runs code from a file" in text, text
    assert "weights_only" not in text and "\n" not in text


def test_several_objects_are_each_named_once(tmp_path) -> None:
    path = tmp_path / "release.pth"
    torch.save({"state_dict": weights(), "args": argparse.Namespace(a=1), "more": argparse.Namespace(b=2),
                "config": RunConfig()}, path)
    with pytest.raises(DataError, match=rf"it holds argparse\.Namespace and {__name__}\.RunConfig, which"):
        read(path)


@pytest.mark.parametrize("legacy", [False, True], ids=["zip", "legacy"])
@pytest.mark.parametrize("keep", [0.5, 100, 3, 0])
def test_a_truncated_or_empty_file_is_not_a_complete_pytorch_file(tmp_path, legacy, keep) -> None:
    whole = tmp_path / "whole.pth"
    torch.save({"state_dict": {**weights(), "big": torch.randn(2000)}}, whole,
               _use_new_zipfile_serialization=not legacy)
    data = whole.read_bytes()
    size = int(len(data) * keep) if isinstance(keep, float) else keep
    cut = tmp_path / "release.pth"
    cut.write_bytes(data[:size])
    with pytest.raises(DataError) as err:
        read(cut)
    text = str(err.value)
    assert f"release.pth: not a readable checkpoint: it is not a complete PyTorch file ({size} bytes)" in text, text
    assert ("the file is empty" in text) == (size == 0) and "EOFError" not in text and "miniz" not in text
    assert read(whole)["big"].shape == (2000,)  # the whole file reads
    (tmp_path / "notes.pth").write_text("weights are on the server\n" * 20)  # a file of another kind is not "cut"
    with pytest.raises(DataError, match="not a readable checkpoint") as err:
        read(tmp_path / "notes.pth")
    assert "complete PyTorch file" not in str(err.value)


def test_batchnorm_statistics_no_trained_model_has_are_refused_with_the_key_named(tmp_path) -> None:
    from distilkit.weights import load_weights

    model = torch.nn.Module()
    model.net = torch.nn.Module()
    model.net.seg_head = torch.nn.Sequential(torch.nn.BatchNorm1d(4))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    bad = weights()
    bad["seg_head.0.running_var"] = torch.tensor([1.0, -0.25, 0.5, -2.0])
    torch.save(bad, tmp_path / "negative.pth")
    with pytest.raises(DataError, match=r"negative\.pth: net\.seg_head\.0\.running_var \(in the file: "
                                        r"seg_head\.0\.running_var\) \(a BatchNorm running variance\) holds 2 "
                                        r"negative values of 4 \(the lowest -2\)"):
        load_weights(model, read(tmp_path / "negative.pth"), True, str(tmp_path / "negative.pth"))
    assert all(torch.equal(v, before[k]) for k, v in model.state_dict().items())  # nothing loaded
    bad = weights()
    bad["seg_head.0.running_mean"] = torch.tensor([0.0, float("nan"), 0.0, 0.0])
    torch.save(bad, tmp_path / "nan.pth")
    with pytest.raises(DataError, match=r"net\.seg_head\.0\.running_mean \(in the file: seg_head\.0\.running_mean\) "
                                        r"holds 1 NaN or infinite values of 4"):
        load_weights(model, read(tmp_path / "nan.pth"), True, "nan.pth")
    dead = weights()
    dead["seg_head.0.running_var"] = torch.tensor([1.0, 0.0, 0.5, 2.0])  # a channel constant in training: kept
    torch.save(dead, tmp_path / "dead.pth")
    assert load_weights(model, read(tmp_path / "dead.pth"), True, "dead.pth") == []
    assert float(model.net.seg_head[0].running_var[1]) == 0.0


@pytest.fixture(scope="module")
def own_weights(tmp_path_factory) -> dict[str, torch.Tensor]:
    """The tiny recipe's teacher's initial weights (a file of them is what a recipe can start from)."""
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    pipe = Pipeline(recipe_from_dict(zero_steps()), tmp_path_factory.mktemp("bn") / "runs", quiet=True)
    return {k: v.clone() for k, v in make_trainer(pipe, "teacher").student.state_dict().items()}


def zero_steps() -> dict:
    """The tiny recipe's teacher alone, evaluated only (steps: 0): what it scores is what its weights score."""
    recipe = tiny_recipe(steps=1, distill=False)
    recipe["stages"]["teacher"]["train"]["steps"] = 0
    return recipe


def test_validate_and_run_refuse_a_negative_running_variance_naming_the_key(own_weights, tmp_path, capsys) -> None:
    state = own_weights
    key = next(k for k in state if k.endswith("running_var"))
    poisoned = dict(state)
    poisoned[key] = state[key].clone()
    poisoned[key][0] = -0.5
    torch.save(poisoned, tmp_path / "poisoned.pt")
    recipe = zero_steps()
    recipe["stages"]["teacher"]["init"] = {"checkpoint": str(tmp_path / "poisoned.pt")}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(tmp_path / "r.yaml"), "--no-memory"]) == 2
    err = capsys.readouterr().err
    assert "stages.teacher.init.checkpoint" in err and f"{key} (a BatchNorm running variance) holds 1 negative" in err
    assert main(["run", str(tmp_path / "r.yaml"), "-o", str(tmp_path / "runs"), "-q"]) == 2  # was: finished
    err = capsys.readouterr().err
    assert f"{key} (a BatchNorm running variance) holds 1 negative" in err and "refusing to load it" in err
    assert "Traceback" not in err
