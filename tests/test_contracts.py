"""The data contract: a dataset registers its collate and fields, adapters declare their inputs.

A camera-style dataset and adapter, defined here and nowhere in distilkit, go through `validate`,
`run` and evaluation with nothing special in the trainer; a LiDAR adapter on camera data is
rejected by `validate`, naming the missing inputs.
"""

from __future__ import annotations

import json
from typing import Any, Iterator

import numpy as np
import pytest
import torch
import yaml
from pydantic import BaseModel, ConfigDict
from torch import Tensor, nn

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: the tests read the recipe's report, not a run's)
from distilkit.adapter import Adapter
from distilkit.cli import main
from distilkit.data.batch import Batch
from distilkit.data.classes import IGNORE_INDEX
from distilkit.data.info import Camera, ClassTable, DataInfo
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import TapError
from distilkit.geometry.voxel import VoxelGrid
from distilkit.losses.task import TaskLoss
from distilkit.metrics.base import Metric
from distilkit.recipe import recipe_from_dict
from distilkit.registry import ADAPTERS, DATASETS, METRICS, TASK_LOSSES
from distilkit.taps import PointCloud, check_tap

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


SPLIT_OFFSET = {"train": 0, "val": 100, "test": 200}  # different samples per split


def camera_split(params: CameraDataParams, split: str, progress: Any = None) -> list[dict[str, np.ndarray]]:
    return [camera_sample(SPLIT_OFFSET[split] + i) for i in range(getattr(params, f"num_{split}"))]


def camera_info(params: CameraDataParams) -> DataInfo:
    return DataInfo(GRID, CLASSES, frozenset({"image", "voxel_label", "invalid", "voxel_target"}), (CAMERA,))


class TinyCameraParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    channels: int = 4


class TinyCamera(Adapter):
    """Image -> 2-D features -> pooled -> a linear lift to voxel logits (a VoxFormer-shaped toy)."""

    Params = TinyCameraParams
    INPUTS = frozenset({"image"})
    TAPS = {"image_features": "image_features", "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"

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
def camera_components() -> Iterator[None]:
    DATASETS.add("tiny-camera-data", camera_split, description="test: images and voxel labels", paper="tests",
                 params=CameraDataParams, info=camera_info, collate=collate_camera, version=1,
                 has_split=lambda p, s: True)
    ADAPTERS.add("tiny-camera", TinyCamera, description="test: camera-style model", paper="tests",
                 consumes=tuple(TinyCamera.TAPS.values()))
    yield
    DATASETS.remove("tiny-camera-data")  # other tests iterate over the registries
    ADAPTERS.remove("tiny-camera")


def validate_fails(recipe: dict[str, Any], tmp_path, capsys) -> str:
    """`distilkit validate` on ``recipe``: exit status 2; returns what it printed."""
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    assert main(["validate", str(path)]) == 2
    captured = capsys.readouterr()
    return captured.out + captured.err


def camera_recipe(adapter: str = "tiny-camera", device: Any = "cpu") -> dict[str, Any]:
    """Teacher and KD student of the camera-style toy, training on ``device`` (the CPU unless a test about the
    computation passes the ``device`` fixture)."""
    train = {"steps": 3, "batch_size": 2, "eval_every": 3, "device": str(device)}
    return {"schema_version": 1, "name": "camera", "seed": 0, "data": {"dataset": "tiny-camera-data", "params": {}},
            "stages": {"teacher": {"model": {"adapter": adapter, "params": {"channels": 6}}, "train": train},
                       "student": {"model": {"adapter": "tiny-camera", "params": {}}, "teacher": {"from": "teacher"},
                                   "distill": [{"name": "kd", "weight": 1.0}], "train": train}}}


def test_camera_style_adapter_trains_distils_and_is_scored(tmp_path, device) -> None:
    results = Pipeline(recipe_from_dict(camera_recipe(device=device)), tmp_path / "runs", quiet=True).run()
    assert [r.name for r in results] == ["teacher", "student"]
    student = results[1].summary
    assert 0.0 <= student["test"]["best"]["miou"] <= 1.0 and len(student["test"]["best"]["class_iou"]) == 2
    assert "kd_kd" in (results[1].run_dir / "metrics.jsonl").read_text()
    report = (tmp_path / "runs" / "camera" / "report.md").read_text()
    assert "| car |" in report and "| road |" in report and "sidewalk" not in report  # the dataset's class table


def test_image_features_serve_feature_objectives_and_must_come_from_one_camera(tmp_path, capsys,
                                                                              monkeypatch) -> None:
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.taps import kind_fits

    assert kind_fits("image_features", "feature_map") and kind_fits("volume_features", "feature_map")
    assert not kind_fits("feature_map", "image_features") and not kind_fits("volume_features", "image_features")
    r = camera_recipe()
    r["stages"]["student"]["distill"].append({"name": "fitnets"})  # reads feature_map roles
    term = resolve(recipe_from_dict(r)).stages["student"].distill[1]
    assert term.taps == {"student": "image_features", "teacher": "image_features"}
    results = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).run()
    assert "kd_fitnets" in (results[1].run_dir / "metrics.jsonl").read_text()  # 4 -> 6 channels via its connector
    right = Camera("cam_right", CAMERA.intrinsics, CAMERA.lidar_to_camera, CAMERA.size)
    monkeypatch.setattr(TinyCamera, "tap_camera",
                        classmethod(lambda c, tap, params, info: right if params.channels == 6 else CAMERA))
    out = validate_fails(r, tmp_path, capsys)
    assert "stages.student.distill[1]" in out and "'cam_right'" in out and "different cameras" in out


def test_a_recorded_tap_of_the_wrong_refinement_is_named_on_the_first_batch(tmp_path) -> None:
    r = camera_recipe()
    r["stages"]["teacher"]["model"]["taps"] = {"enc": {"module": "encoder", "kind": "volume_features"}}
    with pytest.raises(TapError, match=r"teacher.*tap 'enc'.*\(B, C, X, Y, Z\) volume features, got \(2, 6, 12, 16\)"):
        Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True).run()


def test_lidar_adapter_on_camera_data_is_rejected_naming_the_inputs(tmp_path, capsys) -> None:
    out = validate_fails(camera_recipe(adapter="scpnet"), tmp_path, capsys)
    assert "stages.teacher.model.adapter" in out and "point_batch, point_frame, points" in out and "image" in out


def test_batch_field_lookup_names_what_exists() -> None:
    batch = collate_camera([camera_sample(0)])
    assert batch.field("voxel_target") is batch.targets["voxel_target"] and batch.field("size") == 1
    assert batch.fields == {"image", "voxel_label", "invalid", "voxel_target"}
    with pytest.raises(KeyError, match="no field 'scribble'.*inputs: image"):
        batch.field("scribble")
    moved = batch.to(torch.device("cpu"))
    assert torch.equal(moved.inputs["image"], batch.inputs["image"]) and moved.meta["cameras"] == [CAMERA]


# -- a point-cloud completion model, its task loss and metric: all defined here -----------------------


class PointDataParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    num_train: int = 4
    num_val: int = 2
    num_test: int = 2


def point_sample(i: int) -> dict[str, np.ndarray]:
    """A complete cloud symmetric in x and its visible half (x > 0): completion mirrors the partial scan."""
    rng = np.random.default_rng(100 + i)
    half = rng.uniform(0.1, 1.0, size=(int(rng.integers(8, 14)), 3)).astype(np.float32)
    return {"partial": half, "complete": np.concatenate([half, half * np.array([-1, 1, 1], np.float32)])}


def point_split(params: PointDataParams, split: str, progress: Any = None) -> list[dict[str, np.ndarray]]:
    return [point_sample(SPLIT_OFFSET[split] + i) for i in range(getattr(params, f"num_{split}"))]


def collate_points(samples: list[dict[str, np.ndarray]]) -> Batch:
    partial = PointCloud.from_list([torch.from_numpy(s["partial"]) for s in samples])
    complete = PointCloud.from_list([torch.from_numpy(s["complete"]) for s in samples])
    return Batch({"partial": partial.points, "partial_lengths": partial.lengths},
                 {"complete": complete.points, "complete_lengths": complete.lengths}, {"size": len(samples)})


def chamfer(pred: PointCloud, target: PointCloud) -> Tensor:
    """Mean over samples of the symmetric mean nearest-neighbour distance (a naive reference)."""
    per = []
    for b in range(len(pred.lengths)):
        d = torch.cdist(pred.cloud(b), target.cloud(b))
        per.append(d.min(1).values.mean() + d.min(0).values.mean())
    return torch.stack(per).mean()


class TinyPointCompletion(Adapter):
    """Keeps the partial points and adds a learnt linear image of them (ideally the mirror)."""

    Params = TinyCameraParams  # unused width; any params model works
    INPUTS = frozenset({"partial", "partial_lengths"})
    TAPS = {"completion": "points"}
    PREDICTION_TAP = "completion"
    DEFAULT_TASK_LOSSES = [{"name": "test-chamfer"}]

    def __init__(self, params: TinyCameraParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.mirror = nn.Linear(3, 3)

    def forward(self, batch: Batch) -> dict[str, Any]:
        partial = PointCloud(batch.inputs["partial"], batch.inputs["partial_lengths"])
        clouds = [torch.cat([partial.cloud(b), self.mirror(partial.cloud(b))]) for b in range(batch.size)]
        return {"completion": PointCloud.from_list(clouds)}


class _NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ChamferLoss(TaskLoss):
    Params = _NoParams
    CONSUMES = {"student": "points"}
    BATCH = {"complete": "complete", "lengths": "complete_lengths"}

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return chamfer(taps["student"], PointCloud(taps["complete"], taps["lengths"]))


class ChamferScore(Metric):
    SCORES = "points"
    TARGETS = frozenset({"complete", "complete_lengths"})
    KEYS = ("chamfer",)
    LOWER_IS_BETTER = frozenset({"chamfer"})

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.total, self.count = 0.0, 0

    def update(self, prediction: PointCloud, batch: Batch) -> None:
        self.total += float(chamfer(prediction, PointCloud(batch.targets["complete"],
                                                            batch.targets["complete_lengths"]))) * batch.size
        self.count += batch.size

    def compute(self) -> dict[str, Any]:
        return {"chamfer": self.total / max(self.count, 1)}


@pytest.fixture(scope="module", autouse=True)
def point_components() -> Iterator[None]:
    DATASETS.add("tiny-points-data", point_split, description="test: partial and complete point clouds",
                 paper="tests", params=PointDataParams,
                 info=lambda p: DataInfo(None, ClassTable(("point",), ((0, 0, 0),)),
                                         frozenset({"partial", "partial_lengths", "complete", "complete_lengths"})),
                 collate=collate_points, version=1, has_split=lambda p, s: True)
    ADAPTERS.add("tiny-points", TinyPointCompletion, description="test: point completion", paper="tests",
                 consumes=("points",))
    TASK_LOSSES.add("test-chamfer", ChamferLoss, description="test: Chamfer distance", paper="tests",
                    consumes=("points",))
    METRICS.add("test-chamfer", ChamferScore, description="test: Chamfer distance", paper="tests",
                consumes=("points",))
    yield
    for registry, name in ((DATASETS, "tiny-points-data"), (ADAPTERS, "tiny-points"), (TASK_LOSSES, "test-chamfer"),
                           (METRICS, "test-chamfer")):
        registry.remove(name)


def point_recipe(metric: str = "chamfer", device: Any = "cpu") -> dict[str, Any]:
    return {"schema_version": 1, "name": "points", "seed": 0, "data": {"dataset": "tiny-points-data", "params": {}},
            "stages": {"completion": {"model": {"adapter": "tiny-points"}, "optimizer": {"lr": 0.05},
                                      "train": {"steps": 6, "batch_size": 2, "eval_every": 2, "metric": metric,
                                                "device": str(device)}}}}


@pytest.mark.plots
def test_point_cloud_adapter_trains_and_is_scored_by_its_metric(tmp_path, device) -> None:
    (result,) = Pipeline(recipe_from_dict(point_recipe(device=device)), tmp_path / "runs", quiet=True).run()
    evals = [json.loads(line)["eval"] for line in (result.run_dir / "metrics.jsonl").read_text().splitlines()
             if "eval" in line]
    assert len(evals) == 3 and all(set(e) == {"chamfer", "seconds_per_sample"} for e in evals)
    # lower is better: best.pt holds the step with the smallest validation Chamfer distance
    best = min(range(3), key=lambda i: evals[i]["chamfer"])
    assert result.summary["best"]["step"] == 2 * (best + 1)
    assert result.summary["test"]["best"]["chamfer"] > 0
    # the report shows the metric's own score, at both checkpoints, and no SSC columns
    report = (tmp_path / "runs" / "points" / "report.md").read_text()
    assert "best validation chamfer (lowest)" in report and "IoU" not in report and "nan" not in report
    header, _, row = [line for line in report.splitlines() if line.startswith("|")][:3]
    cells = dict(zip(header.strip("|").split(" | "), row.strip("|").split(" | ")))
    assert float(cells["chamfer best"]) == pytest.approx(result.summary["test"]["best"]["chamfer"], rel=1e-3)
    assert float(cells["chamfer last"]) == pytest.approx(result.summary["test"]["last"]["chamfer"], rel=1e-3)
    assert float(cells["val chamfer"]) == pytest.approx(evals[best]["chamfer"], rel=1e-3)
    assert (tmp_path / "runs" / "points" / "report.png").stat().st_size > 0


def test_a_metric_that_does_not_fit_the_prediction_is_rejected(tmp_path, capsys) -> None:
    out = validate_fails(point_recipe(metric="miou"), tmp_path, capsys)
    assert "stages.completion.train.metric" in out and "points predictions" in out and "test-chamfer.chamfer" in out


def test_point_cloud_values_are_checked() -> None:
    cloud = PointCloud.from_list([torch.ones(2, 3), torch.ones(5, 3)])
    assert cloud.points.shape == (2, 5, 3) and cloud.lengths.tolist() == [2, 5] and cloud.cloud(0).shape == (2, 3)
    with pytest.raises(ValueError, match="lengths must lie in 0..5"):
        PointCloud(cloud.points, torch.tensor([2, 6]))
    with pytest.raises(TapError, match="expected PointCloud.*got \\(2, 5, 3\\) for a points tap"):
        check_tap(cloud.points, "points", "tap 'completion'")
