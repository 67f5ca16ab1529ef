"""The data contract: a dataset registers its collate and fields, adapters declare their inputs.

A camera-style dataset and adapter, defined here and nowhere in distilkit, go through `validate`,
`run` and evaluation with nothing special in the trainer; a LiDAR adapter on camera data is
rejected by `validate`, naming the missing inputs.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch
import yaml
from pydantic import BaseModel, ConfigDict
from torch import nn

from distilkit.adapter import Adapter
from distilkit.cli import main
from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX
from distilkit.data.info import Camera, ClassTable, DataInfo
from distilkit.engine.pipeline import Pipeline
from distilkit.geometry.voxel import VoxelGrid
from distilkit.recipe import recipe_from_dict
from distilkit.registry import ADAPTERS, DATASETS

GRID = VoxelGrid((0.0, -3.2, -2.0), (8, 8, 2), 0.8)
CLASSES = ClassTable(("empty", "car", "road"), ((0, 0, 0), (100, 150, 245), (255, 0, 255)))
CAMERA = Camera("front", ((20.0, 0.0, 8.0), (0.0, 20.0, 6.0), (0.0, 0.0, 1.0)),
                ((0.0, -1.0, 0.0, 0.0), (0.0, 0.0, -1.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)), (12, 16))


class CameraDataParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    num_train: int = 4
    num_val: int = 2
    num_test: int = 2


def camera_sample(i: int) -> dict[str, np.ndarray]:
    """An image whose brightness tells the class of the lower voxel layer (learnable in a few steps)."""
    rng = np.random.default_rng(i)
    label = rng.integers(0, 3, size=GRID.shape).astype(np.uint8)
    image = (rng.normal(size=(3, *CAMERA.size)) + label[:, :, 0].mean()).astype(np.float32)
    return {"image": image, "voxel_label": label, "invalid": np.zeros(GRID.shape, bool)}


def collate_camera(samples: list[dict[str, np.ndarray]]) -> Batch:
    label = torch.stack([torch.from_numpy(s["voxel_label"].astype(np.int64)) for s in samples])
    invalid = torch.stack([torch.from_numpy(s["invalid"]) for s in samples])
    return Batch({"image": torch.stack([torch.from_numpy(s["image"]) for s in samples])},
                 {"voxel_label": label, "invalid": invalid, "voxel_target": label.masked_fill(invalid, IGNORE_INDEX)},
                 {"size": len(samples), "cameras": [CAMERA] * len(samples)})


def camera_info(params: CameraDataParams) -> DataInfo:
    return DataInfo(GRID, CLASSES, frozenset({"image", "voxel_label", "invalid", "voxel_target"}), (CAMERA,))


class TinyCameraParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    channels: int = 4


class TinyCamera(Adapter):
    """Image -> 2-D features -> pooled -> a linear lift to voxel logits (a VoxFormer-shaped toy)."""

    Params = TinyCameraParams
    INPUTS = frozenset({"image"})
    TAPS = {"image_features": "feature_map", "logits": "voxel_logits"}
    LOGITS_TAP = "logits"

    def __init__(self, params: TinyCameraParams, info: DataInfo) -> None:
        super().__init__(params, info)
        assert info.grid is not None and info.cameras, "camera data with a voxel grid"
        self.encoder = nn.Conv2d(3, params.channels, 3, padding=1)
        self.lift = nn.Linear(params.channels, info.num_classes * int(np.prod(info.grid.shape)))

    def forward(self, batch: Batch) -> dict[str, Any]:
        feats = torch.relu(self.encoder(batch.inputs["image"]))
        logits = self.lift(feats.mean(dim=(2, 3))).view(batch.size, self.info.num_classes, *self.info.grid.shape)
        return {"image_features": feats, "logits": logits}


@pytest.fixture(scope="module", autouse=True)
def camera_components() -> None:
    if "tiny-camera-data" not in DATASETS:
        DATASETS.add("tiny-camera-data", lambda p, split, progress=None: [camera_sample(i + hash(split) % 97)
                                                                           for i in range(getattr(p, f"num_{split}"))],
                     description="test: images and voxel labels", paper="tests", params=CameraDataParams,
                     info=camera_info, collate=collate_camera, version=1, has_split=lambda p, s: True)
    if "tiny-camera" not in ADAPTERS:
        ADAPTERS.add("tiny-camera", TinyCamera, description="test: camera-style model", paper="tests",
                     consumes=tuple(TinyCamera.TAPS.values()))


def camera_recipe(adapter: str = "tiny-camera") -> dict[str, Any]:
    train = {"steps": 3, "batch_size": 2, "eval_every": 3}
    return {"schema_version": 1, "name": "camera", "seed": 0, "data": {"dataset": "tiny-camera-data", "params": {}},
            "stages": {"teacher": {"model": {"adapter": adapter, "params": {"channels": 6}}, "train": train},
                       "student": {"model": {"adapter": "tiny-camera", "params": {}}, "teacher": {"from": "teacher"},
                                   "distill": [{"name": "kd", "weight": 1.0}], "train": train}}}


def test_camera_style_adapter_trains_distils_and_is_scored(tmp_path) -> None:
    results = Pipeline(recipe_from_dict(camera_recipe()), tmp_path / "runs", quiet=True).run()
    assert [r.name for r in results] == ["teacher", "student"]
    student = results[1].summary
    assert 0.0 <= student["test"]["best"]["miou"] <= 1.0 and len(student["test"]["best"]["class_iou"]) == 2
    assert "kd_kd" in (results[1].run_dir / "metrics.jsonl").read_text()
    report = (tmp_path / "runs" / "camera" / "report.md").read_text()
    assert "| car |" in report and "| road |" in report and "sidewalk" not in report  # the dataset's class table


def test_lidar_adapter_on_camera_data_is_rejected_naming_the_inputs(tmp_path, capsys) -> None:
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(camera_recipe(adapter="scpnet")))
    assert main(["validate", str(path)]) == 2
    captured = capsys.readouterr()
    out = captured.out + captured.err
    assert "stages.teacher.model.adapter" in out and "point_batch, point_frame, points" in out and "image" in out


def test_batch_field_lookup_names_what_exists() -> None:
    batch = collate_camera([camera_sample(0)])
    assert batch.field("voxel_target") is batch.targets["voxel_target"] and batch.field("size") == 1
    assert batch.fields == {"image", "voxel_label", "invalid", "voxel_target"}
    with pytest.raises(KeyError, match="no field 'scribble'.*inputs: image"):
        batch.field("scribble")
    moved = batch.to(torch.device("cpu"))
    assert torch.equal(moved.inputs["image"], batch.inputs["image"]) and moved.meta["cameras"] == [CAMERA]
