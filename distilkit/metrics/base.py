"""The metric contract: a registered accumulator that scores one kind of prediction.

A metric declares the tap kind of the prediction it scores (``SCORES``), the batch targets it reads
(``TARGETS``), and the scalar scores ``compute`` returns (``KEYS``; those in ``LOWER_IS_BETTER`` are
minimised when they select the best checkpoint). An adapter names its prediction tap
(``Adapter.PREDICTION_TAP``, of any kind); ``train.metric`` picks a score among the metrics registered
for that kind, so a point-cloud model is scored by a point-cloud metric with nothing special in the trainer.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo


class Metric(ABC):
    SCORES: ClassVar[str]
    TARGETS: ClassVar[frozenset[str]] = frozenset()
    KEYS: ClassVar[tuple[str, ...]] = ()
    LOWER_IS_BETTER: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, info: DataInfo) -> None:
        self.info = info

    @abstractmethod
    def update(self, prediction: Any, batch: Batch) -> None:
        """Accumulate one batch: ``prediction`` is the value of the adapter's prediction tap."""

    @abstractmethod
    def compute(self) -> dict[str, Any]:
        """Scores over everything accumulated: at least every key of ``KEYS`` (floats)."""
