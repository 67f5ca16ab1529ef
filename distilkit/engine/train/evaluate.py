"""Scoring a model on a split: its prediction tap, accumulated by a list of registered metrics.

Each process scores its contiguous share of the split (:func:`~distilkit.engine.train.loader.eval_batches`); the metrics'
states are merged across processes in rank order (:meth:`~distilkit.metrics.base.Metric.merge`), so every scene is
scored once and the scores equal one process's. A stochastic model (a diffusion sampler) draws its noise from a
stream seeded with ``seed`` that training does not see: every evaluation of a stage draws the same noise, and
evaluating does not change what is trained next.
"""

from __future__ import annotations

import contextlib
import time
from typing import Any, Callable, Iterator

import torch

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.engine.train.distributed import SINGLE, World
from distilkit.engine.train.loader import eval_batches
from distilkit.metrics.base import Metric

Collate = Callable[[list[Any]], Batch]


@contextlib.contextmanager
def seeded(seed: int, device: torch.device) -> Iterator[None]:
    """A random stream of its own, seeded with ``seed``; the caller's is given back after."""
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


def _merged(metrics: list[Metric], seconds: float, count: int, world: World) -> tuple[list[Metric], float, int]:
    """The metrics' states, forward seconds and sample counts of every process, merged in rank order."""
    if not world.distributed:
        return metrics, seconds, count
    parts: list[Any] = [None] * world.size
    torch.distributed.all_gather_object(parts, (metrics, seconds, count))
    merged, total_s, total_n = parts[0]
    for others, s, n in parts[1:]:
        for mine, other in zip(merged, others):
            mine.merge(other)
        total_s, total_n = total_s + s, total_n + n
    return merged, total_s, total_n


@torch.no_grad()
def evaluate(model: Adapter, dataset: Any, batch_size: int, device: torch.device, collate: Collate,
             metrics: list[Any], world: World = SINGLE, workers: int = 0, seed: int = 0,
             prepare: Callable[[Batch], Batch] | None = None,
             progress: Callable[[int | None, int | None], None] | None = None,
             scenes: bool = False) -> dict[str, Any]:
    """Scores of the model's prediction tap over ``dataset`` with ``metrics`` (each with its registered ``name``
    and ``cls``): the first one's keys as they are, the others' as ``<name>.<key>``; and ``seconds_per_sample`` of
    the model's forward passes, its auxiliary models' included (``prepare``). ``progress(done, total)`` follows this
    process's samples (``(None, None)`` at the end). ``scenes``: also ``scenes``, the first metric's per-scene counts
    (:meth:`~distilkit.metrics.base.Metric.per_scene`), where it keeps them."""
    was_training = model.training
    model.eval()
    accs = [m.cls(model.info) for m in metrics]
    seconds, count = 0.0, 0
    share = -(-len(dataset) // world.size)
    with seeded(seed, device):
        for batch in eval_batches(dataset, batch_size, collate, world, workers):
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            t0 = time.perf_counter()  # the frozen auxiliary models' passes (in ``prepare``) count: they predict too
            batch = prepare(batch) if prepare is not None else batch.to(device)
            out = model(batch)
            if device.type == "cuda":
                torch.cuda.synchronize(device)
            seconds += time.perf_counter() - t0
            count += batch.size
            if model.PREDICTION_TAP not in out:
                from distilkit.errors import TapError

                raise TapError(f"{type(model).__name__} in evaluation returned no prediction tap "
                               f"{model.PREDICTION_TAP!r} (returned: {', '.join(map(str, out))})")
            for acc in accs:
                acc.update(out[model.PREDICTION_TAP], batch)
            if progress is not None:
                progress(min(count, share), share)
    if progress is not None:
        progress(None, None)
    model.train(was_training)
    accs, seconds, count = _merged(accs, seconds, count, world)
    scores: dict[str, Any] = dict(accs[0].compute())
    for m, acc in zip(metrics[1:], accs[1:]):
        scores.update({f"{m.name}.{k}": v for k, v in acc.compute().items()})
    per_scene = accs[0].per_scene() if scenes else None
    if per_scene is not None:
        scores["scenes"] = per_scene
    # the forward time per sample (not the metric's), e.g. a sampler's seconds per scene (+ a refiner's)
    return {**scores, "seconds_per_sample": seconds / max(count, 1)}


@torch.no_grad()
def preview(model: Adapter, dataset: Any, device: torch.device, collate: Collate,
            metric: type[Metric], seed: int = 0,
            prepare: Callable[[Batch], Batch] | None = None) -> dict[str, Any] | None:
    """The metric's bird's-eye preview of the model on the first sample of ``dataset`` (None: none to show)."""
    if len(dataset) == 0:
        return None
    was_training = model.training
    model.eval()
    batch = collate([dataset[0]])
    batch = prepare(batch) if prepare is not None else batch.to(device)
    with seeded(seed, device):
        out = model(batch)
    model.train(was_training)
    return metric.preview(out[model.PREDICTION_TAP], batch, model.info)
