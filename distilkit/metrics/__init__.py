"""Evaluation metrics: SemanticKITTI SSC (confusion, IoU, precision, recall, mIoU) and point-cloud completion
(Chamfer distance, BEV Jensen-Shannon distance, voxel IoU, precision/recall over 5-10 cm)."""

from distilkit.metrics.points import auc, chamfer_distance, jsd_bev, precision_recall_curves, voxel_confusion
from distilkit.metrics.ssc import SSCMetric, ssc_confusion, ssc_scores

__all__ = ["SSCMetric", "ssc_confusion", "ssc_scores", "chamfer_distance", "jsd_bev", "voxel_confusion",
           "precision_recall_curves", "auc"]
