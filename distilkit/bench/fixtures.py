"""Inputs that several benchmarks build the same way: a LiDAR-like street of points, recipes/scorelidar.yaml's
LiDiff models, and each family's network on one sample at the papers' sizes (:func:`network_cases`, :func:`build`:
``distilkit bench networks`` and ``step``). Not a benchmark: no case is registered here."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import Tensor


def street(m: int, seed: int, device: torch.device) -> Tensor:
    """A LiDAR-like scene of ``m`` points: a ground plane, walls and poles within 50 m (metres)."""
    g = torch.Generator().manual_seed(seed)
    part = m // 3
    ground = torch.cat([torch.rand(part, 2, generator=g) * 100 - 50, torch.randn(part, 1, generator=g) * 0.02 - 1.7], 1)
    wall = torch.cat([torch.rand(part, 1, generator=g) * 100 - 50, 8 + torch.randn(part, 1, generator=g) * 0.05,
                      torch.rand(part, 1, generator=g) * 4 - 1.7], 1)
    rest = m - 2 * part
    centres = (torch.rand(rest // 50 + 1, 2, generator=g) * 80 - 40).repeat_interleave(50, 0)[:rest]
    poles = torch.cat([centres + torch.randn(rest, 2, generator=g) * 0.1, torch.rand(rest, 1, generator=g) * 5 - 1.7], 1)
    return torch.cat([ground, wall, poles]).to(device)


def lidiff_models(device: torch.device, scan: int) -> tuple[Any, Any]:
    """recipes/scorelidar.yaml's LiDiff denoiser and refiner, built through the adapter registry (random weights: the
    time does not depend on them)."""
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info
    from distilkit.registry import ADAPTERS

    info = scenes_info(SceneParams(scan_points=scan, scene_points=10 * scan))
    with torch.random.fork_rng(devices=[]):
        lidiff, refine = ADAPTERS.get("lidiff"), ADAPTERS.get("lidiff-refine")
        model = lidiff(lidiff.Params(channels=32, blocks=2, duplicate=10, sample_steps=8), info).to(device).eval()
        refiner = refine(refine.Params(channels=32), info).to(device).eval()
    return model, refiner



@dataclass
class NetworkCase:
    family: str
    adapter: str
    dataset: str
    size: str  # "tiny" | "paper"
    data: dict[str, Any]
    params: dict[str, Any] = field(default_factory=dict)
    what: str = ""


def data_sizes(quick: bool, test: bool = False) -> dict[str, dict[str, Any]]:
    """The data parameters of the papers' inputs (``lidar``: a 64-beam scan of the synthetic streets on the
    256 x 256 x 32 grid; ``camera``: the same with a 370 x 1220 image; ``scenes``: an 18,000-point scan completed to
    180,000 points), ``quick``: a quarter of each (128 x 128 x 16, 184 x 610, 4,500 points), ``test``: the tests'
    sizes (32 x 32 x 4, a 16-beam scan of 256 azimuth steps, 24 x 80, 400 points), seconds on a CPU."""
    if test:
        lidar = {"scale": 8, "beams": 16, "azimuth_steps": 256, "input_frames": 1, "gt_frames": 3, "num_train": 1,
                 "num_val": 1, "num_test": 1}
        scenes = {"scan_points": 400, "scene_points": 4000, "beams": 16, "azimuth_steps": 256, "frames": 3,
                  "num_train": 1, "num_val": 1, "num_test": 1}
        return {"lidar": lidar, "camera": {**lidar, "camera": {"height": 24, "width": 80, "previous": []}},
                "scenes": scenes}
    lidar = {"scale": 2 if quick else 1, "beams": 64, "azimuth_steps": 1024 if quick else 2048, "input_frames": 1,
             "gt_frames": 0 if quick else 4, "num_train": 1, "num_val": 1, "num_test": 1}
    camera = {**lidar, "camera": {"height": 184 if quick else 370, "width": 610 if quick else 1220, "previous": []}}
    scan = 4500 if quick else 18000
    scenes = {"scan_points": scan, "scene_points": 10 * scan, "num_train": 1, "num_val": 1, "num_test": 1,
              "azimuth_steps": 1024 if quick else 2048}
    return {"lidar": lidar, "camera": camera, "scenes": scenes}


PAPER_RECIPES = Path(__file__).resolve().parents[2] / "recipes" / "paper"  # the checkout's paper recipes


def paper_recipe(name: str, quick: bool, test: bool, device: str = "cpu", num_train: int | None = None,
                 tiny: bool = False) -> dict[str, Any]:
    """Paper recipe ``name`` (``recipes/paper/NAME.yaml``) as a dict with its ``data`` at the bench's sizes
    (:func:`data_sizes`): its synthetic scenes resized, or its SemanticKITTI folder replaced by the synthetic streets
    at the same sizes with the recipe's scans (``input_frames``) and camera frames; every stage on ``device``;
    ``num_train``: that many training samples; ``tiny``: every network at ``size: tiny``."""
    import yaml

    recipe = yaml.safe_load((PAPER_RECIPES / f"{name}.yaml").read_text())
    sizes, params = data_sizes(quick, test), dict(recipe["data"].get("params") or {})
    if recipe["data"]["dataset"] == "synthetic-scenes":
        data = {"dataset": "synthetic-scenes", "params": {**params, **sizes["scenes"]}}
    else:
        lidar = {**sizes["lidar"], "input_frames": int(params.get("input_frames", 1))}
        if params.get("camera") is not None:
            lidar["camera"] = {**sizes["camera"]["camera"], "previous": list(params["camera"].get("previous", []))}
        data = {"dataset": "synthetic-lidar", "params": lidar}
    if num_train is not None:
        data["params"]["num_train"] = num_train
    recipe["data"] = data
    for spec in recipe["stages"].values():
        spec.setdefault("train", {})["device"] = device
        model_params = (spec.get("model") or {}).get("params") or {}
        if tiny and "size" in model_params:
            model_params["size"] = "tiny"
    return recipe


def network_cases(quick: bool, test: bool = False, sizes: tuple[str, ...] = ("tiny", "paper")) -> list[NetworkCase]:
    """The families at ``sizes`` on the papers' data sizes (quick: a quarter of them; test: the tests' sizes, see
    :func:`data_sizes`)."""
    data = data_sizes(quick, test)
    lidar, camera, scenes = data["lidar"], data["camera"], data["scenes"]
    grid = "x".join(str(n // lidar["scale"]) for n in (256, 256, 32))
    lidar_what = f"{lidar['beams']}-beam scan ({lidar['azimuth_steps']:,} steps), {grid}"
    scan = scenes["scan_points"]
    cases = []
    for size in sizes:
        cases += [
            NetworkCase("SCPNet", "scpnet", "synthetic-lidar", size, lidar, {"size": size}, lidar_what),
            NetworkCase("JS3C-Net", "js3cnet", "synthetic-lidar", size, lidar, {"size": size}, lidar_what),
            NetworkCase("LiDiff", "lidiff", "synthetic-scenes", size, scenes, {"size": size},
                        f"{scan:,} -> {10 * scan:,} points"),
            NetworkCase("LiDiff refine", "lidiff-refine", "synthetic-scenes", size, scenes, {"size": size},
                        f"{10 * scan:,} points"),
            NetworkCase("VoxFormer", "voxformer", "synthetic-lidar", size, camera,
                        {"size": size, "geometry": "ground-truth"},
                        f"{camera['camera']['height']}x{camera['camera']['width']} image, {grid}"),
            NetworkCase("Dean-Labeler", "dean-labeler", "synthetic-lidar", size, lidar, {"size": size},
                        f"complete geometry, {grid}"),
        ]
    return cases


def sample_batch(case: NetworkCase, device: torch.device, batch_size: int = 1) -> tuple[Any, Any]:
    """(the case's first training sample collated ``batch_size`` times — the cost of a batch of that size without
    generating more scenes —, on ``device``; the data's info)."""
    from distilkit.registry import DATASETS

    entry = DATASETS.entry(case.dataset)
    params = entry.meta["params"](**case.data)
    info = entry.meta["info"](params)
    sample = entry.obj(params, "train")[0]
    return entry.meta["collate"]([sample] * batch_size).to(device), info


def tap_loss(taps: dict[str, Any]) -> Tensor:
    """The mean of every floating-point tap with a gradient (tensors, the ``feats`` of sparse taps, the ``points`` of
    point clouds), summed: a loss whose backward reaches every parameter the taps depend on."""
    terms = []
    for value in taps.values():
        value = getattr(value, "feats", getattr(value, "points", value))
        if isinstance(value, Tensor) and value.is_floating_point() and value.requires_grad:
            terms.append(value.float().mean())
    return torch.stack(terms).sum()


def build(case: NetworkCase, device: torch.device, batch_size: int = 1) -> tuple[Any, Any]:
    """(model in training mode on ``device``, random weights from seed 0; a collated batch of ``batch_size``)."""
    from distilkit.registry import ADAPTERS

    batch, info = sample_batch(case, device, batch_size)
    cls = ADAPTERS.get(case.adapter)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = cls(cls.Params(**case.params), info).to(device).train()
    return model, batch


__all__ = ["NetworkCase", "build", "data_sizes", "lidiff_models", "network_cases", "sample_batch", "street",
           "tap_loss"]
