"""Registry entries for the metrics."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.metrics.base import Metric
from distilkit.metrics.ssc import SSCMetric
from distilkit.registry import METRICS


class SSCScore(Metric):
    """Voxel logits scored as SemanticKITTI SSC: the argmax class per voxel against ``voxel_label``, voxels
    flagged ``invalid`` left out, one confusion matrix over the split."""

    SCORES = "voxel_logits"
    TARGETS = frozenset({"voxel_label", "invalid"})
    KEYS = ("miou", "iou", "precision", "recall")
    TITLE = "SSC metrics in %"
    COLUMNS = (("miou", "mIoU", 100.0), ("iou", "IoU", 100.0), ("precision", "precision", 100.0),
               ("recall", "recall", 100.0))
    PER_CLASS, PER_CLASS_FROM = ("class_iou", "IoU", 100.0), 1  # classes 1..K-1 (0 = empty is not semantic)

    def __init__(self, info: DataInfo) -> None:
        super().__init__(info)
        self.acc = SSCMetric(info.num_classes, info.classes.ignore_index)

    def update(self, prediction: Tensor, batch: Batch) -> None:
        self.acc.update(prediction.argmax(dim=1).cpu(), batch.targets["voxel_label"].cpu(),
                        batch.targets["invalid"].cpu())

    def compute(self) -> dict[str, Any]:
        return self.acc.compute()


METRICS.add(
    "ssc",
    SSCScore,
    description="SemanticKITTI SSC: completion IoU/precision/recall and semantic mIoU over classes 1..K-1",
    paper="Behley et al., SemanticKITTI, ICCV 2019 (evaluate_completion.py)",
    consumes=(SSCScore.SCORES,),
)
