"""Samples that carry their id: every split a stage reads gives each sample a ``sample_id`` (the dataset's own, e.g.
a SemanticKITTI ``sequence/frame``, else ``<split>/<index>``), and every batch lists them in ``meta["sample_id"]``.
Published predictions are stored, and overlaid on other stages' data, by these ids."""

from __future__ import annotations

from typing import Any, Callable

import torch

from distilkit.data.batch import Batch


class Split(torch.utils.data.Dataset):
    """A dataset's split whose samples carry ``sample_id``."""

    def __init__(self, dataset: Any, split: str) -> None:
        self.dataset, self.split = dataset, split

    def __len__(self) -> int:
        return len(self.dataset)

    def sample_id(self, i: int) -> str:
        own = getattr(self.dataset, "sample_id", None)
        return str(own(i)) if callable(own) else f"{self.split}/{i:06d}"

    def __getitem__(self, i: int) -> dict[str, Any]:
        return {**self.dataset[i], "sample_id": self.sample_id(i)}

    def __getattr__(self, name: str) -> Any:  # the dataset's own attributes (info, arrays, ...)
        if name in ("dataset", "split"):
            raise AttributeError(name)
        return getattr(self.dataset, name)


class IdCollate:
    """A dataset's collate that also lists the samples' ids in ``meta["sample_id"]`` and, for augmented samples,
    their draws in ``meta["augment_draw"]`` (picklable for loader workers)."""

    def __init__(self, collate: Callable[[list[Any]], Batch]) -> None:
        self.collate = collate

    def __call__(self, samples: list[dict[str, Any]]) -> Batch:
        batch = self.collate(samples)
        batch.meta.setdefault("sample_id", [str(s.get("sample_id", "")) for s in samples])
        if any("augment_draw" in s for s in samples):  # the transform each sample is seen under (train.augment)
            batch.meta["augment_draw"] = [int(s.get("augment_draw", 0)) for s in samples]
        return batch


__all__ = ["IdCollate", "Split"]
