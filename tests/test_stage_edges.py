"""Edges between stages beyond teacher and init: labels from a stage's published predictions, and a frozen
auxiliary model whose taps become batch inputs (Scribble2Scene's Dean-Labeler and VoxFormer's query proposals,
in miniature on the camera-style toy of test_contracts)."""

from __future__ import annotations

from typing import Any, Iterator

import numpy as np
import pytest
import torch
import yaml
from torch import nn

import test_contracts as tc
from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from distilkit.cli import main
from distilkit.data.batch import Batch
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.store.predictions import LabelOverlay, PredictionStore
from distilkit.engine.assemble.runs import load_run
from distilkit.engine.train.trainer import Trainer
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.registry import ADAPTERS, DATASETS


class Proposed(tc.TinyCamera):
    """The camera toy that also reads a frozen network's voxel logits (``proposal``) and adds them, scaled."""

    INPUTS = frozenset({"image", "proposal"})

    def __init__(self, params: Any, info: Any) -> None:
        super().__init__(params, info)
        self.scale = nn.Parameter(torch.tensor(0.5))

    def forward(self, batch: Batch) -> dict[str, Any]:
        out = super().forward(batch)
        return {**out, "logits": out["logits"] + self.scale * batch.inputs["proposal"]}


@pytest.fixture(autouse=True)
def components() -> Iterator[None]:
    DATASETS.add("tiny-camera-data", tc.camera_split, description="test", paper="tests", params=tc.CameraDataParams,
                 info=tc.camera_info, collate=tc.collate_camera, version=1, has_split=lambda p, s: True)
    ADAPTERS.add("tiny-camera", tc.TinyCamera, description="test", paper="tests",
                 consumes=tuple(tc.TinyCamera.TAPS.values()))
    ADAPTERS.add("tiny-proposed", Proposed, description="test", paper="tests", consumes=tuple(Proposed.TAPS.values()))
    yield
    for reg, name in ((DATASETS, "tiny-camera-data"), (ADAPTERS, "tiny-camera"), (ADAPTERS, "tiny-proposed")):
        reg.remove(name)


def recipe() -> dict[str, Any]:
    # on the CPU whatever --device says: these tests compare published predictions and fed inputs with the same
    # networks run here on the CPU, bit for bit
    train = {"steps": 2, "batch_size": 2, "eval_every": 2, "workers": 0, "device": "cpu"}
    camera = {"adapter": "tiny-camera", "params": {}}
    return {"schema_version": 1, "name": "edges", "seed": 0, "data": {"dataset": "tiny-camera-data", "params": {}},
            "stages": {"labeler": {"model": camera, "train": train},
                       "proposer": {"model": {**camera, "params": {"channels": 6}}, "train": train},
                       "student": {"model": {"adapter": "tiny-proposed", "params": {}}, "train": train,
                                   "labels": {"from": "labeler"}, "aux": {"proposal": {"from": "proposer"}}}}}


def test_labels_from_a_stage_and_a_frozen_auxiliary_model(tmp_path, monkeypatch, capsys) -> None:
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe()))
    assert main(["validate", str(path), "--no-memory"]) == 0
    plan = capsys.readouterr().out
    assert "student (tiny-proposed; labels <- labeler; aux.proposal <- proposer)" in plan

    seen: list[Batch] = []
    step = Trainer.train_step
    monkeypatch.setattr(Trainer, "train_step", lambda self, batch, i: (seen.append(batch), step(self, batch, i))[1])
    pipe = Pipeline(recipe_from_dict(recipe()), tmp_path / "runs", quiet=True)
    assert pipe.resolved.order.index("student") == 2
    results = {r.name: r for r in pipe.run()}
    assert set(results) == {"labeler", "proposer", "student"}

    # the labeler published its best model's predictions of the training split, by sample id, without pickle
    folder = results["labeler"].run_dir / "predictions" / "train"
    store = PredictionStore(folder)
    data, info = pipe.dataset("train"), pipe.resolved.data_info
    assert sorted(store.ids) == [data[i]["sample_id"] for i in range(len(data))] == ["train/000000", "train/000001",
                                                                                        "train/000002", "train/000003"]
    labeler = load_run(results["labeler"].run_dir, model=pipe.resolved.stages["labeler"].student, info=info)
    batch = pipe.collate([data[i] for i in range(len(data))])
    with torch.no_grad():
        want = labeler(batch)["logits"].argmax(1)
    for i, sample_id in enumerate(batch.meta["sample_id"]):
        got = np.load(folder / f"{sample_id.replace('/', '__')}.npy", allow_pickle=False)
        assert got.dtype == np.uint8 and np.array_equal(got, want[i].numpy())
    assert not (results["proposer"].run_dir / "predictions").exists()  # nobody asked for its predictions

    # the student trained on those labels, with the proposer's logits as its input
    proposer = load_run(results["proposer"].run_dir, model=pipe.resolved.stages["proposer"].student, info=info)
    student_batches = seen[-2:]
    for b in student_batches:
        ids = b.meta["sample_id"]
        assert torch.equal(b.targets["voxel_label"], torch.stack([torch.from_numpy(store.get(i)).long() for i in ids]))
        raw = pipe.collate([data[int(i.split("/")[1])] for i in ids])
        assert not torch.equal(raw.targets["voxel_label"], b.targets["voxel_label"])  # the data's own are replaced
        with torch.no_grad():
            assert torch.equal(b.inputs["proposal"], proposer(raw)["logits"])
    # evaluation read the data's own labels (labels.splits: train only) and the proposals too
    assert "miou" in results["student"].summary["test"]["best"]


def test_a_finished_stage_publishes_what_a_later_recipe_asks_and_validate_names_bad_edges(tmp_path) -> None:
    r = recipe()
    student = r["stages"].pop("student")
    Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).run()  # labeler and proposer: nobody asks
    (labeler,) = (tmp_path / "runs" / "edges").glob("labeler-*")
    assert not (labeler / "predictions").exists()
    r["stages"]["student"] = student
    results = {x.name: x for x in Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).run()}
    assert results["labeler"].reused and results["labeler"].run_dir == labeler
    assert (labeler / "predictions" / "train" / "index.json").is_file()

    bad = recipe()
    bad["stages"]["student"].pop("aux")
    with pytest.raises(RecipeError, match=r"stages.student.model.adapter: adapter 'tiny-proposed' reads batch "
                                          r"input\(s\) proposal"):
        Pipeline(recipe_from_dict(bad), tmp_path / "x", quiet=True)
    bad = recipe()
    bad["stages"]["student"]["aux"]["proposal"]["inputs"] = {"logitz": "proposal"}
    bad["stages"]["student"]["labels"]["keep"] = "scribble"
    with pytest.raises(RecipeError) as err:
        Pipeline(recipe_from_dict(bad), tmp_path / "x", quiet=True)
    assert "stages.student.aux.proposal.inputs: stage 'proposer'" in str(err.value)
    assert "stages.student.labels.keep: the data has no field 'scribble'" in str(err.value)
    bad["stages"]["student"]["labels"]["from"] = "labeller"
    with pytest.raises(RecipeError, match=r"stages.student.labels.from: no stage named 'labeller'; did you mean"):
        Pipeline(recipe_from_dict(bad), tmp_path / "x", quiet=True)


def test_the_overlay_keeps_the_datas_labelled_values(tmp_path) -> None:
    from distilkit.engine.store.predictions import publish

    class Const(nn.Module):
        PREDICTION_TAP = "logits"

        def forward(self, batch: Batch) -> dict[str, Any]:
            logits = torch.zeros(batch.size, 3, 2, 2, 1)
            logits[:, 2] = 1.0  # class 2 everywhere
            return {"logits": logits}

    samples = [{"sample_id": f"s/{i}", "voxel_label": np.zeros((2, 2, 1), np.uint8),
                "scribble": np.array([[[1], [254]], [[255], [0]]], np.uint8)} for i in range(2)]
    batch = Batch({}, {}, {"size": 2, "sample_id": ["s/0", "s/1"]})
    assert publish(Const(), [batch], tmp_path / "p", "voxel_logits") == 2
    overlay = LabelOverlay(samples, PredictionStore(tmp_path / "p"), "voxel_label", "scribble", 255, 254)
    # scribbled voxels (1 and 0) keep their label; unlabelled (254) and invalid (255) ones take the prediction
    assert overlay[1]["voxel_label"][:, :, 0].tolist() == [[1, 2], [2, 0]]
    plain = LabelOverlay(samples, PredictionStore(tmp_path / "p"), "voxel_label", None, 255, 254)
    assert plain[0]["voxel_label"][:, :, 0].tolist() == [[2, 2], [2, 2]]
    # a voxel the data itself leaves unlabelled (its ignore index) stays so: the prediction cannot label it
    ignored = [{**samples[0], "voxel_label": np.array([[[255], [0]], [[0], [0]]], np.uint8)}]
    assert LabelOverlay(ignored, PredictionStore(tmp_path / "p"), "voxel_label", None, 255, 254)[0][
        "voxel_label"][:, :, 0].tolist() == [[255, 2], [2, 2]]
    with pytest.raises(Exception, match="no prediction for sample 'other/0'"):
        LabelOverlay([{**samples[0], "sample_id": "other/0"}], PredictionStore(tmp_path / "p"), "voxel_label",
                     None, 255, 254)[0]
