"""The metric contract: a registered accumulator that scores one kind of prediction.

A metric declares the tap kind of the prediction it scores (``SCORES``), the batch targets it reads
(``TARGETS``), and the scalar scores ``compute`` returns (``KEYS``; those in ``LOWER_IS_BETTER`` are
minimised when they select the best checkpoint); ``TITLE``, ``COLUMNS`` and ``PER_CLASS`` say how reports
show them. An adapter names its prediction tap
(``Adapter.PREDICTION_TAP``, of any kind); ``train.metric`` picks a score among the metrics registered
for that kind, so a point-cloud model is scored by a point-cloud metric with nothing special in the trainer.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

from distilkit.cards.base import MetricCard
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo


class Metric(MetricCard, ABC):
    """A registered accumulator (its declarations are :class:`~distilkit.cards.base.MetricCard`'s)."""

    def __init__(self, info: DataInfo) -> None:
        self.info = info

    @abstractmethod
    def update(self, prediction: Any, batch: Batch) -> None:
        """Accumulate one batch: ``prediction`` is the value of the adapter's prediction tap."""

    @abstractmethod
    def compute(self) -> dict[str, Any]:
        """Scores over everything accumulated: at least every key of ``KEYS`` (floats)."""

    def per_scene(self) -> dict[str, Any] | None:
        """Each scored sample's counts from which the split's score is computed (``ids`` and arrays with one row
        per sample), for a bootstrap over the scenes; None: this metric keeps none."""
        return None

    def merge(self, other: "Metric") -> None:
        """Add the state another process accumulated over other samples (multi-process evaluation merges in rank
        order, over contiguous shares: lists concatenate in sample order). The default merges every attribute:
        tensors and numbers add, lists extend, dicts merge key by key; override it for other state."""
        for name, value in vars(other).items():
            if name != "info":
                setattr(self, name, _merge(getattr(self, name), value, f"{type(self).__name__}.{name}"))

    @classmethod
    def preview(cls, prediction: Any, batch: Batch, info: DataInfo) -> dict[str, Any] | None:
        """A bird's-eye view of the batch's first sample for the run report (``distilkit.report.plots``):
        ``input``, ``prediction`` and ``target`` panels, each a (H, W) class-id image (-1 = nothing there) or an
        (N, 3) point array, and ``extent`` (x0, x1, y0, y1) in metres. None: this metric shows no preview."""
        return None


def _merge(mine: Any, other: Any, where: str) -> Any:
    import torch

    if isinstance(mine, (torch.Tensor, int, float)) and not isinstance(mine, bool):
        return mine + other
    if isinstance(mine, list):
        return mine + list(other)
    if isinstance(mine, dict):
        return {k: _merge(mine[k], other[k], f"{where}[{k!r}]") if k in mine else other[k] for k in {**mine, **other}}
    if hasattr(mine, "__dict__"):  # an accumulator object (e.g. a confusion matrix holder): merge its attributes
        for name, value in vars(other).items():
            setattr(mine, name, _merge(getattr(mine, name), value, f"{where}.{name}"))
        return mine
    if mine == other:  # a setting (class count, ignore index)
        return mine
    raise TypeError(f"{where}: cannot merge {type(mine).__name__} values across processes; override Metric.merge")
