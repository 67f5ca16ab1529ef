"""``distilkit bench determinism | loader | camera``: training steps of the recipes' stages — with the deterministic
settings on and off, through the loader's worker processes and without, the camera student with and without
RGO²D."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.bench.base import Case, register, scratch_dir
from distilkit.repro import set_deterministic


@register("determinism")
def determinism_cases(device: torch.device, quick: bool) -> list[Case]:
    """The cost of bitwise-repeatable runs (:mod:`distilkit.repro`): one training step of the quickstart's SCPNet
    student and of recipes/js3cnet_dskd.yaml's JS3C-Net student (batch 2, two scenes of their data), with PyTorch's
    deterministic algorithms off ('fast') and on ('naive'), alternately on the same trainer. MKL's strict mode
    (``MKL_CBWR``) is read when the process starts and is not toggled here."""
    from distilkit.data.probe import _one_scene
    from distilkit.engine.memory.probe import probe_trainer
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    data = {"dataset": "synthetic-lidar", "params": {"scale": 8 if quick else 4, "input_frames": 4, "gt_frames": 10,
                                                     "azimuth_steps": 768}}
    models = {"SCPNet student": {"adapter": "scpnet", "params": {"frames": 1, "channels": 8, "point_mlp": [32, 64],
                                                                  "seg_channels": 16}},
              "JS3C-Net student": {"adapter": "js3cnet", "params": {"frames": 1}}}
    cases = []
    for label, model in models.items():
        recipe = {"name": "bench", "data": data, "stages": {"s": {"model": model, "train": {"batch_size": 2,
                                                                                              "device": device.type}}}}
        res = resolve(recipe_from_dict(recipe, "bench"), "bench")
        params = _one_scene(res.data_params).model_copy(update={"num_train": 2})
        trainer = probe_trainer(res, "s", params, scratch_dir("run-"), batch_size=2)
        batch = trainer.first_batch()
        trainer.student.train()

        def step(on: bool, trainer=trainer, batch=batch) -> Tensor:
            set_deterministic(on, warn_only=True)
            torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]  # as repro does
            try:
                return torch.tensor(trainer.train_step(batch, 0)["loss"])
            finally:
                set_deterministic(False)

        size = f"train step, batch 2, {'x'.join(map(str, res.data_info.grid.shape))}"
        cases.append(Case(f"determinism: {label}", size, lambda step=step: step(False), lambda step=step: step(True),
                          [], same_value=False))
    return cases


@register("loader")
def loader_cases(device: torch.device, quick: bool) -> list[Case]:
    """Training steps of the quickstart's teacher (a 4-frame SCPNet, batch 2, recipes/quickstart.yaml's data) through
    the stage's loader with 2 worker processes ('fast') and with none ('naive'): the batches are read and collated
    in the workers while the step runs. Each timing covers the loader's start and one epoch of steps (6; the quick
    mode: 2 steps on an 8-times smaller grid of smaller scans)."""
    from distilkit.engine.train.loader import BatchPlan, train_batches
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.engine.train.trainer import Trainer
    from distilkit.recipe import recipe_from_dict

    data = {"scale": 8 if quick else 4, "num_train": 4 if quick else 12, "num_val": 1, "num_test": 1,
            "input_frames": 4, "gt_frames": 3 if quick else 10, "azimuth_steps": 256 if quick else 768,
            **({"beams": 16} if quick else {})}  # quick: scenes made in a fifth of the time (the path, not the figure)
    model = {"adapter": "scpnet", "params": {"frames": 4, "channels": 8, "point_mlp": [32, 64], "seg_channels": 16}}
    recipe = {"name": "bench", "data": {"dataset": "synthetic-lidar", "params": data},
              "stages": {"s": {"model": model, "train": {"batch_size": 2, "grad_clip": 10, "device": device.type}}}}
    pipe = Pipeline(recipe_from_dict(recipe, "bench"), scratch_dir("run-"), quiet=True)
    stage, train_set = pipe.resolved.stages["s"], pipe.dataset("train")
    plan = BatchPlan(len(train_set), 2, 0)
    torch.manual_seed(0)
    trainer = Trainer(stage, pipe.resolved.data_info, train_set, plan, device, collate=pipe.collate)
    steps = 2 if quick else plan.steps_per_epoch

    def run(workers: int) -> Tensor:
        losses = [trainer.train_step(batch.to(device), i)["loss"]
                  for i, batch in enumerate(train_batches(train_set, plan, pipe.collate, 0, steps, workers))]
        return torch.tensor(sum(losses) / len(losses))

    size = f"{steps} train steps, batch 2, {'x'.join(map(str, pipe.resolved.data_info.grid.shape))}"
    return [Case("loader: 2 workers vs none", size, lambda: run(2), lambda: run(0), [], same_value=False)]


@register("camera")
def camera_cases(device: torch.device, quick: bool) -> list[Case]:
    """One training step of recipes/scribble2scene.yaml's camera student (VoxFormer-style, tiny, 2 images, frozen
    query proposals; batch 4 on its 64 x 64 x 8 grid, the quick mode 32 x 32 x 4) with RGO²D from the
    Teacher-Labeler and the image-feature MSE ('naive') and without distillation ('fast'): what distilling costs.
    Models have random weights (the step's cost does not depend on them)."""
    from distilkit.data.probe import _one_scene
    from distilkit.engine.memory.probe import probe_trainer
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    data = {"dataset": "synthetic-lidar", "params": {"scale": 8 if quick else 4, "input_frames": 1,
                                                     "gt_frames": 4 if quick else 10, "camera": {"previous": [3]}}}
    student = {"model": {"adapter": "voxformer", "params": {"frames": 2}}, "aux": {"proposal": {"from": "proposal"}},
               "task_losses": [{"name": "weighted_ce"}, {"name": "geo_scal"}],
               "train": {"batch_size": 4, "device": device.type}}
    features = {"student_features": "image_features", "teacher_features": "image_features"}
    stages = {"proposal": {"model": {"adapter": "voxformer-proposal"}, "train": {"metric": "iou"}},
              "teacher_labeler": {"model": {"adapter": "voxformer", "params": {"geometry": "ground-truth",
                                                                               "frames": 2}}},
              "plain": student,
              "rgo2d": {**student, "teacher": {"from": "teacher_labeler"},
                        "distill": [{"name": "rgo2d", "taps": features}]}}
    res = resolve(recipe_from_dict({"name": "bench", "data": data, "stages": stages}, "bench"), "bench")
    params = _one_scene(res.data_params).model_copy(update={"num_train": 4})
    steps = {}
    for name in ("plain", "rgo2d"):
        trainer = probe_trainer(res, name, params, scratch_dir("run-"), batch_size=4)
        batch = trainer.first_batch()
        trainer.student.train()
        steps[name] = lambda trainer=trainer, batch=batch: torch.tensor(trainer.train_step(batch, 0)["loss"])
    size = f"train step, batch 4, 2 images, {'x'.join(map(str, res.data_info.grid.shape))}"
    return [Case("camera student: no KD vs RGO²D", size, steps["plain"], steps["rgo2d"], [], same_value=False)]

