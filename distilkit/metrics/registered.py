"""Registry entries for the metrics."""

from distilkit.metrics.ssc import SSCMetric
from distilkit.registry import METRICS

METRICS.add(
    "ssc",
    SSCMetric,
    description="SemanticKITTI SSC: completion IoU/precision/recall and semantic mIoU over classes 1..K-1",
    paper="Behley et al., SemanticKITTI, ICCV 2019 (evaluate_completion.py)",
    consumes=("voxel_logits",),
)
