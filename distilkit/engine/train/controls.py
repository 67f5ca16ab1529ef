"""Control teachers (``teacher: {control: random | shuffled}``, issue 59): the stage's objectives at their weights,
against a teacher that knows nothing of the sample. A gain over the undistilled student that the control gives as
well is the extra loss term's regularisation, not the teacher's knowledge (Mason-Williams et al., "A Functional
Perspective on Knowledge Distillation", arXiv 2510.12615, 2026: their random-control teacher).

- ``random``: the teacher's architecture (and recorded taps) with the random weights its adapter initialises, drawn
  from :func:`control_seed` of the stage's seed: never the checkpoint's weights, and not the student's own
  initialisation where both have one architecture.
- ``shuffled``: the real teacher, but training sample ``i`` is given the outputs the teacher gives for sample
  ``σ(i)`` under the same augmentation draw; ``σ`` (:func:`cycle`) is one random cycle through the whole training
  split (Sattolo 1986), fixed by the stage's seed, so no sample meets its own outputs and every sample's outputs
  are used once an epoch: the teacher's output distribution is kept, its pairing with the input is removed.
  Live, the teacher runs on the partner's batch (:class:`Partnered`, :class:`WithPartner`); with ``store`` the
  student reads the partner's rows of the real teacher's store (:class:`PartnerStore`, the same values).

Sparse taps of another scene lie at that scene's voxels: terms that gather the teacher's sparse features at the
student's voxels (DSKD, :func:`~distilkit.objectives.common.aligned_pairs`) read the other scene's features where
both scenes occupy a voxel and zero elsewhere; dense taps are read voxel for voxel, as the paper's control does.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch

from distilkit.errors import DataError

STREAM = 0x636F6E74  # the controls' own random stream ("cont")
PARTNER = "_control_partner"  # a sample's partner, carried from the dataset to the collate


def control_seed(seed: int) -> int:
    """The seed of a control's draws: the stage's ``seed`` in a stream of its own."""
    return int(np.random.SeedSequence([seed % 2 ** 64, STREAM]).generate_state(1)[0])


def cycle(n: int, seed: int) -> list[int]:
    """``σ`` of the shuffled control: a uniformly random ``n``-cycle (Sattolo's algorithm) from ``seed``'s stream —
    a permutation without a fixed point."""
    if n < 2:
        raise DataError(f"`teacher.control: shuffled` gives each training sample another's teacher outputs: the "
                        f"training split has {n} sample(s), it needs two at least")
    rng = np.random.default_rng([seed % 2 ** 64, STREAM])
    sigma = list(range(n))
    for i in range(n - 1, 0, -1):
        j = int(rng.integers(0, i))  # j < i: Sattolo's, where Fisher–Yates would allow j = i
        sigma[i], sigma[j] = sigma[j], sigma[i]
    return sigma


def random_teacher(model: Any, info: Any, seed: int, device: torch.device) -> Any:
    """The ``random`` control: ``model`` (the resolved teacher) built with fresh random weights from
    :func:`control_seed`, frozen, on ``device``; the caller's random stream is left as it was."""
    from distilkit.engine.assemble.runs import build_model, freeze

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(control_seed(seed))
        built = build_model(model, info, "random control teacher")
    return freeze(built.to(device))


class Partnered(torch.utils.data.Dataset):
    """A training split whose item ``i`` (or ``(i, draw)``) also carries item ``σ(i)`` (under the same draw), for the
    shuffled control's live teacher."""

    def __init__(self, dataset: Any, sigma: list[int]) -> None:
        if len(sigma) != len(dataset):
            raise ValueError(f"σ has {len(sigma)} entries for {len(dataset)} samples")
        self.dataset, self.sigma = dataset, sigma

    def __len__(self) -> int:
        return len(self.dataset)

    def partner(self, item: Any) -> Any:
        return (self.sigma[item[0]], item[1]) if isinstance(item, tuple) else self.sigma[item]

    def __getitem__(self, item: Any) -> dict[str, Any]:
        return {**self.dataset[item], PARTNER: self.dataset[self.partner(item)]}

    def __getattr__(self, name: str) -> Any:  # the split's own attributes (info, sample_id, ...)
        if name in ("dataset", "sigma"):
            raise AttributeError(name)
        return getattr(self.dataset, name)


class WithPartner:
    """A training collate for :class:`Partnered` samples: the batch as the collate makes it, and the partners' batch
    in ``meta["teacher_batch"]`` (what the trainer's teacher reads instead)."""

    def __init__(self, collate: Callable[[list[Any]], Any]) -> None:
        self.collate = collate

    def __call__(self, samples: list[dict[str, Any]]) -> Any:
        batch = self.collate([{k: v for k, v in s.items() if k != PARTNER} for s in samples])
        batch.meta["teacher_batch"] = self.collate([s[PARTNER] for s in samples])
        return batch


class PartnerStore:
    """A teacher store read, for each sample of a batch, at its partner's rows (``σ`` over the store's samples,
    which are the training split's in order)."""

    def __init__(self, store: Any, sigma: list[int]) -> None:
        ids = [str(s) for s in store.manifest["samples"]]
        if len(sigma) != len(ids):
            raise DataError(f"{store.folder}: the store holds {len(ids)} samples, the training split has {len(sigma)}")
        self.store, self.partner = store, {ids[i]: ids[j] for i, j in enumerate(sigma)}

    def of(self, batch: Any, device: torch.device) -> dict[str, Any]:
        return self.store.of(batch, device, rename=self.partner)


__all__ = ["PARTNER", "PartnerStore", "Partnered", "STREAM", "WithPartner", "control_seed", "cycle", "random_teacher"]
