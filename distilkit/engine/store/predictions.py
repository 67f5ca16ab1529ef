"""Published predictions: a finished stage's best model predicts every sample of a split, stored by sample id, and a
later stage trains on them (``labels: {from: STAGE}``; Scribble2Scene's student on the Dean-Labeler's pseudo-labels).

On disk, ``<run>/predictions/<split>/``: one ``.npy`` per sample (loaded with ``allow_pickle=False``) named after
its id (``/`` written as ``__``), and ``index.json`` with the ids, the tap and its kind. What a prediction is comes
from the tap's kind: ``voxel_logits`` -> the class per voxel (uint8), ``points`` -> the point cloud (float32, N x 3).

The overlay (:class:`LabelOverlay`) replaces a sample field (``voxel_label`` by default) of the consuming stage's
training split with the prediction of the same sample, except where the data's own ``keep`` field is labelled (its
value neither the class table's ignore index nor ``unlabelled``): there the data's label wins.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from distilkit.errors import DataError
from distilkit.taps import publishable  # noqa: F401  (re-exported: what can be published)


def _file(sample_id: str) -> str:
    return sample_id.replace("/", "__") + ".npy"


def per_sample(value: Any, kind: str, b: int) -> np.ndarray:
    """Sample ``b``'s prediction from a prediction tap of ``kind``."""
    if kind == "voxel_logits":
        return value[b].argmax(dim=0).to(torch.uint8).cpu().numpy()
    if kind == "points":
        return value.cloud(b).detach().float().cpu().numpy()
    raise DataError(f"predictions of a {kind} tap cannot be published (voxel_logits and points can)")


@torch.no_grad()
def publish(model: Any, batches: Any, folder: Path, kind: str, prepare: Callable[[Any], Any] = lambda b: b) -> int:
    """Write ``model``'s prediction of every sample of ``batches`` into ``folder``; the number written."""
    from distilkit.files import atomic_write, atomic_write_json

    folder.mkdir(parents=True, exist_ok=True)
    was = model.training
    model.eval()
    ids: list[str] = []
    for batch in batches:
        batch = prepare(batch)
        out = model(batch)[model.PREDICTION_TAP]
        for b, sample_id in enumerate(batch.meta["sample_id"]):
            value = per_sample(out, kind, b)
            atomic_write(folder / _file(sample_id), lambda f, value=value: np.save(f, value, allow_pickle=False))
            ids.append(sample_id)
    model.train(was)
    atomic_write_json(folder / "index.json", {"ids": ids, "tap": model.PREDICTION_TAP, "kind": kind})
    return len(ids)


class PredictionStore:
    """A published split: ``get(sample_id)`` -> the stored prediction."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        index = folder / "index.json"
        if not index.is_file():
            raise DataError(f"{folder}: no published predictions here (index.json is missing)")
        try:
            self.index = json.loads(index.read_text())
        except ValueError as exc:
            raise DataError(f"{index}: not readable ({exc})") from None
        self.ids = set(self.index["ids"])

    def get(self, sample_id: str) -> np.ndarray:
        if sample_id not in self.ids:
            raise DataError(f"{self.folder}: no prediction for sample {sample_id!r} (it holds {len(self.ids)} samples "
                            "of another split or data set)")
        path = self.folder / _file(sample_id)
        try:
            return np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DataError(f"{path}: not a readable prediction ({exc})") from None


def is_published(folder: Path) -> bool:
    return (folder / "index.json").is_file()


class LabelOverlay(torch.utils.data.Dataset):
    """Samples of ``dataset`` whose ``field`` is the published prediction, except where ``keep`` is labelled (its
    value wins) and where the data's own ``field`` is the ignore index (it stays ignored: no label to replace)."""

    def __init__(self, dataset: Any, store: PredictionStore, field: str, keep: str | None, ignore_index: int,
                 unlabelled: int | None) -> None:
        self.dataset, self.store, self.field, self.keep = dataset, store, field, keep
        self.ignore_index, self.unlabelled = ignore_index, unlabelled

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, i: int) -> dict[str, Any]:
        sample = dict(self.dataset[i])
        pred = self.store.get(sample["sample_id"])
        own = sample.get(self.field)
        if own is not None and np.shape(own) != pred.shape:
            raise DataError(f"sample {sample['sample_id']!r}: the published prediction has shape {pred.shape}, the "
                            f"data's {self.field!r} {np.shape(own)}")
        label = pred.astype(own.dtype if own is not None else pred.dtype)
        if own is not None:  # what the data itself cannot label (its ignore index) stays unlabelled
            label = np.where(np.asarray(own) == self.ignore_index, own, label).astype(label.dtype)
        if self.keep is not None:
            data = np.asarray(sample[self.keep])
            labelled = data != self.ignore_index
            if self.unlabelled is not None:
                labelled &= data != self.unlabelled
            label = np.where(labelled, data, label).astype(label.dtype)
        sample[self.field] = label
        return sample

    def __getattr__(self, name: str) -> Any:
        if name in ("dataset", "store", "field", "keep", "ignore_index", "unlabelled"):
            raise AttributeError(name)
        return getattr(self.dataset, name)


__all__ = ["LabelOverlay", "PredictionStore", "is_published", "per_sample", "publish", "publishable"]
