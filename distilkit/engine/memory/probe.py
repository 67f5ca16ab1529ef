"""A stage's trainer on a small copy of its data, built without any upstream run (the teacher with random weights:
the same tensors, other numbers) — what the memory estimate and the training-step benchmark measure."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any


def probe_trainer(res: Any, stage_name: str, params: Any, run_dir: Path, batch_size: int = 1) -> Any:
    """A :class:`~distilkit.engine.train.trainer.Trainer` of ``stage_name`` on the data ``params`` (e.g. one of its
    dataset's probe plans), at ``batch_size``; it writes nothing (``run_dir`` is kept for callers' files)."""
    import torch

    from distilkit.engine.train.distributed import SINGLE
    from distilkit.engine.train.loader import BatchPlan
    from distilkit.engine.assemble.runs import build_model, freeze
    from distilkit.engine.assemble.devices import pick_device
    from distilkit.engine.train.auxiliary import with_aux_inputs
    from distilkit.engine.train.trainer import Trainer
    from distilkit.registry import DATASETS

    stage = res.stages[stage_name]
    entry = DATASETS.entry(res.recipe.data.dataset)
    info = entry.meta["info"](params)
    train_set = entry.obj(params, "train", None)
    spec = stage.spec.model_copy(update={"train": stage.spec.train.model_copy(update={"batch_size": batch_size})})
    stage = dataclasses.replace(stage, spec=spec)
    device = pick_device(spec.train.device)
    torch.manual_seed(0)
    teacher = None
    if stage.teacher is not None and stage.distill and stage.ema is None:  # an EMA: the trainer's
        teacher = freeze(build_model(stage.teacher, info, "teacher").to(device))
    aux = [(a, freeze(build_model(a.model, info, f"aux model {a.name!r}").to(device))) for a in stage.aux]
    plan = BatchPlan(len(train_set), batch_size, 0, SINGLE)
    return Trainer(stage, info, train_set, plan, device, collate=entry.meta["collate"], teacher=teacher, world=SINGLE,
                   prepare=lambda batch: with_aux_inputs(batch.to(device), aux, training=True))


__all__ = ["probe_trainer"]
