"""Scoring a model on a split: its prediction tap, accumulated by a registered metric."""

from __future__ import annotations

import time
from typing import Any, Callable

import torch

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.metrics.base import Metric

Collate = Callable[[list[Any]], Batch]


@torch.no_grad()
def evaluate(model: Adapter, dataset: Any, batch_size: int, device: torch.device, collate: Collate,
             metric: type[Metric]) -> dict[str, Any]:
    """Scores of the model's prediction tap over ``dataset`` with a registered metric, and ``seconds_per_sample``
    of the model's forward passes."""
    was_training = model.training
    model.eval()
    acc = metric(model.info)
    seconds = 0.0
    for start in range(0, len(dataset), batch_size):
        batch = collate([dataset[i] for i in range(start, min(start + batch_size, len(dataset)))]).to(device)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        out = model(batch)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        seconds += time.perf_counter() - t0
        if model.PREDICTION_TAP not in out:
            from distilkit.errors import TapError

            raise TapError(f"{type(model).__name__} in evaluation returned no prediction tap {model.PREDICTION_TAP!r} "
                           f"(returned: {', '.join(map(str, out))})")
        acc.update(out[model.PREDICTION_TAP], batch)
    model.train(was_training)
    # the model's forward time per sample (not the metric's), e.g. a sampler's seconds per scene
    return {**acc.compute(), "seconds_per_sample": seconds / max(len(dataset), 1)}


@torch.no_grad()
def preview(model: Adapter, dataset: Any, device: torch.device, collate: Collate,
            metric: type[Metric]) -> dict[str, Any] | None:
    """The metric's bird's-eye preview of the model on the first sample of ``dataset`` (None: none to show)."""
    if len(dataset) == 0:
        return None
    was_training = model.training
    model.eval()
    batch = collate([dataset[0]]).to(device)
    out = model(batch)
    model.train(was_training)
    return metric.preview(out[model.PREDICTION_TAP], batch, model.info)
