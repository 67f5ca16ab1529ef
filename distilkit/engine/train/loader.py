"""Batches of a stage: a seeded, resumable order of training batches and PyTorch data loaders over it.

The order (:class:`BatchPlan`) is a pure function of the seed and the step: epoch ``e`` is a permutation of the
training split drawn from a generator seeded with ``seed * 100_003 + e``; step ``s`` of the epoch takes the
``batch_size`` samples after ``s * batch_size`` (the last batch of an epoch may be smaller), and process ``r`` of
``N`` takes every ``N``-th of them from the ``r``-th. A run resumed at step ``k`` continues with batch ``k``, and the
order is the same with any number of loader workers. A stage that augments (``train.augment``) draws each sample's
transform from its own generator seeded with the seed and the step (:meth:`BatchPlan.elements`), so the draws too
repeat bit for bit and resume with the run: samples are read and collated in the workers
(``train.workers``), in order, and moved to the device in the stage's process.

Evaluation shards a split into contiguous blocks, one per process (:func:`eval_indices`), so each scene is scored
once and the merged metric equals one process's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Iterator

import numpy as np
import torch

from distilkit.data.batch import Batch
from distilkit.engine.train.distributed import SINGLE, World

Collate = Callable[[list[Any]], Batch]


def default_workers() -> int:
    """Loader processes when ``train.workers`` is ``auto``: none on 2 CPUs or fewer (the stage's threads need
    them), else half of the usable CPUs beyond two, at most 4."""
    from distilkit.engine.train.cpus import usable_cpus

    return min(4, max(0, (usable_cpus() - 2 + 1) // 2))


def resolve_workers(value: int | str) -> int:
    return default_workers() if value == "auto" else int(value)


@dataclass(frozen=True)
class BatchPlan:
    """The training batches of a stage: which samples step ``s`` reads, in this process."""

    size: int  # samples in the training split
    batch_size: int  # the global batch
    seed: int
    world: World = SINGLE
    group: int = 1  # the values an augmentation draw takes (1: none): a finite group's order, or 2**32 seeds

    @property
    def steps_per_epoch(self) -> int:
        return math.ceil(self.size / self.batch_size)

    def _global(self, step: int) -> list[int]:
        epoch, i = divmod(step, self.steps_per_epoch)
        g = torch.Generator().manual_seed(self.seed * 100_003 + epoch)
        perm = torch.randperm(self.size, generator=g)
        bs = self.batch_size
        return [int(j) for j in perm[i * bs:(i + 1) * bs]]

    def indices(self, step: int) -> list[int]:
        """This process's sample indices of global batch ``step`` (0-based)."""
        return self.world.shard(self._global(step))

    def elements(self, step: int) -> list[int]:
        """The augmentation draw each sample of global batch ``step`` is seen under, in this process (a finite
        group's element, or a continuous transform's seed; all 0 without augmentation): a pure function of the seed
        and the step, so a resumed run draws the same."""
        n = len(self._global(step))
        if self.group == 1:
            return self.world.shard([0] * n)
        rng = np.random.default_rng([self.seed % 2 ** 64, step, 0x617567])  # its own stream; any seed, negative too
        return self.world.shard([int(e) for e in rng.integers(self.group, size=n, dtype=np.int64)])

    def items(self, step: int) -> list[Any]:
        """What the loader asks the split for at ``step``: sample indices, or ``(index, element)`` pairs when the
        stage augments (:class:`~distilkit.data.augment.Augmented`)."""
        if self.group == 1:
            return self.indices(step)
        return list(zip(self.indices(step), self.elements(step)))

    def batch(self, dataset: Any, collate: Collate, step: int) -> Batch:
        """Batch ``step`` read in this process (the terms' setup pass reads batch 0 this way)."""
        return collate([dataset[j] for j in self.items(step)])


class _Steps(torch.utils.data.Sampler):
    """Batch sampler: the plan's indices for steps ``start`` .. ``stop - 1``."""

    def __init__(self, plan: BatchPlan, start: int, stop: int) -> None:
        self.plan, self.start, self.stop = plan, start, stop

    def __iter__(self) -> Iterator[list[Any]]:
        return (self.plan.items(s) for s in range(self.start, self.stop))

    def __len__(self) -> int:
        return max(0, self.stop - self.start)


class _Blocks(torch.utils.data.Sampler):
    """Batch sampler over given indices, ``batch_size`` at a time, in order."""

    def __init__(self, indices: list[int], batch_size: int) -> None:
        self.indices, self.batch_size = indices, batch_size

    def __iter__(self) -> Iterator[list[int]]:
        return (self.indices[i:i + self.batch_size] for i in range(0, len(self.indices), self.batch_size))

    def __len__(self) -> int:
        return math.ceil(len(self.indices) / self.batch_size)


def _loader(dataset: Any, sampler: torch.utils.data.Sampler, collate: Collate, workers: int) -> Any:
    # the loader's own generator: iterating it never draws from the stage's random stream (a resumed run's RNG
    # state is the one its checkpoint saved, whatever the loader did)
    return torch.utils.data.DataLoader(dataset, batch_sampler=sampler, collate_fn=collate, num_workers=workers,
                                       generator=torch.Generator().manual_seed(0),
                                       persistent_workers=False, prefetch_factor=2 if workers else None)


def train_batches(dataset: Any, plan: BatchPlan, collate: Collate, start: int, stop: int,
                  workers: int) -> Iterator[Batch]:
    """Batches of steps ``start`` .. ``stop - 1`` in this process, read by ``workers`` loader processes (0: here)."""
    return iter(_loader(dataset, _Steps(plan, start, stop), collate, workers))


def eval_indices(n: int, world: World) -> list[int]:
    """This process's contiguous block of a split of ``n`` samples (blocks in rank order cover it once)."""
    lo, hi = n * world.rank // world.size, n * (world.rank + 1) // world.size
    return list(range(lo, hi))


def eval_batches(dataset: Any, batch_size: int, collate: Collate, world: World = SINGLE,
                 workers: int = 0) -> Iterator[Batch]:
    """This process's share of a split in batches of ``batch_size``, in order."""
    return iter(_loader(dataset, _Blocks(eval_indices(len(dataset), world), batch_size), collate, workers))


__all__ = ["BatchPlan", "Collate", "default_workers", "eval_batches", "eval_indices", "resolve_workers",
           "train_batches"]
