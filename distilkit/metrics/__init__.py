"""Evaluation metrics: SemanticKITTI SSC confusion, IoU, precision, recall and mIoU."""

from distilkit.metrics.ssc import SSCMetric, ssc_confusion, ssc_scores

__all__ = ["SSCMetric", "ssc_confusion", "ssc_scores"]
