"""The metrics' cards (torch-free): the prediction kind each scores, the targets it reads, its keys and how reports
show them, and its registration; the implementations (:mod:`distilkit.metrics.registered`, imported when a run
scores) subclass them."""

from __future__ import annotations

from distilkit.cards.base import MetricCard
from distilkit.registry import METRICS

_IMPL = "distilkit.metrics.registered"


def range_key(r: float) -> str:
    """The score-key suffix of a range: 12.8 -> ``12_8m`` (keys hold no dots: ``train.metric`` splits on them)."""
    return f"{r:g}".replace(".", "_") + "m"


class SSCScoreCard(MetricCard):
    """SemanticKITTI SSC's declarations: its scores over the whole grid and VoxFormer's inner boxes (``RANGES``)."""

    SCORES = "voxel_logits"
    SELECTS = "miou"
    TARGETS = frozenset({"voxel_label", "invalid"})
    RANGES = (12.8, 25.6)  # VoxFormer's inner boxes; the whole grid (51.2 m on SemanticKITTI) is miou / iou
    KEYS = ("miou", "iou", "precision", "recall", *(f"{s}_{range_key(r)}" for r in RANGES for s in ("miou", "iou")))
    TITLE = "SSC metrics in %"
    COLUMNS = (("miou", "mIoU", 100.0), ("iou", "IoU", 100.0), ("precision", "precision", 100.0),
               ("recall", "recall", 100.0),
               *((f"{s}_{range_key(r)}", f"{name} {r:g} m", 100.0) for r in RANGES
                 for s, name in (("miou", "mIoU"), ("iou", "IoU"))))
    PER_CLASS, PER_CLASS_FROM = ("class_iou", "IoU", 100.0), 1  # classes 1..K-1 (0 = empty is not semantic)


class OccupancyScoreCard(MetricCard):
    """The query proposals' empty / occupied scores' declarations."""

    SCORES = "occupancy_logits"
    SELECTS = "iou"
    TARGETS = frozenset({"voxel_label", "invalid"})
    KEYS = ("iou", "precision", "recall")
    TITLE = "occupancy (query proposals) in %"
    COLUMNS = (("iou", "IoU", 100.0), ("precision", "precision", 100.0), ("recall", "recall", 100.0))


class SceneCompletionScoreCard(MetricCard):
    """LiDiff's scene-completion scores' declarations: the voxel sizes of its IoUs (``VOXELS``) and the 3-D range
    beyond which predicted points are dropped (``MAX_RANGE``, metres)."""

    SCORES = "points"
    SELECTS = "cd"
    TARGETS = frozenset({"scene_eval", "scene_eval_lengths"})
    KEYS = ("cd", "jsd", "iou_50cm", "iou_20cm", "iou_10cm", "precision", "recall", "fscore", "jsd_3d",
            "iou_50cm_rounded", "iou_20cm_rounded", "iou_10cm_rounded")
    LOWER_IS_BETTER = frozenset({"cd", "jsd", "jsd_3d"})
    TITLE = "scene completion (LiDiff's evaluation: CD in m, IoU, precision, recall and F in %)"
    COLUMNS = (("cd", "CD", 1.0), ("jsd", "JSD", 1.0), ("iou_50cm", "IoU 0.5 m", 100.0),
               ("iou_20cm", "IoU 0.2 m", 100.0), ("iou_10cm", "IoU 0.1 m", 100.0), ("precision", "precision", 100.0),
               ("recall", "recall", 100.0), ("fscore", "F", 100.0), ("seconds_per_sample", "s / scene", 1.0))
    VOXELS = {"iou_50cm": 0.5, "iou_20cm": 0.2, "iou_10cm": 0.1}
    MAX_RANGE = 50.0


class EMDScoreCard(MetricCard):
    """The earth mover's distance's declarations."""

    SCORES = "points"
    TARGETS = frozenset({"scene_eval", "scene_eval_lengths"})
    KEYS = ("emd",)
    LOWER_IS_BETTER = frozenset({"emd"})
    TITLE = "earth mover's distance (m, 2,048-point subsamples)"
    COLUMNS = (("emd", "EMD", 1.0),)


METRICS.declare(
    "ssc",
    f"{_IMPL}:SSCScore",
    card=SSCScoreCard,
    description="SemanticKITTI SSC: completion IoU/precision/recall and semantic mIoU over classes 1..K-1",
    paper="Behley et al., SemanticKITTI, ICCV 2019 (evaluate_completion.py)",
    consumes=(SSCScoreCard.SCORES,),
)


METRICS.declare(
    "occupancy",
    f"{_IMPL}:OccupancyScore",
    card=OccupancyScoreCard,
    description="binary occupancy (query proposals) at the scores' resolution: IoU, precision, recall",
    paper="VoxFormer (Li et al. CVPR 2023), stage 1 (labels pooled as its half-resolution geometry)",
    consumes=(OccupancyScoreCard.SCORES,),
)


METRICS.declare(
    "emd",
    f"{_IMPL}:EMDScore",
    card=EMDScoreCard,
    description="earth mover's distance of point-cloud completions (exact, 2,048-point subsamples)",
    paper="reported by Distillation-DPO (Zhang et al., arXiv 2504.11447); its released Sinkhorn is degenerate",
    consumes=(EMDScoreCard.SCORES,),
)


METRICS.declare(
    "completion",
    f"{_IMPL}:SceneCompletionScore",
    card=SceneCompletionScoreCard,
    description="point-cloud scene completion: Chamfer and BEV Jensen-Shannon distances, voxel IoU at 0.5/0.2/0.1 m, "
                "precision/recall/F over 5-10 cm",
    paper="Nunes et al., LiDiff, CVPR 2024 (eval_path.py, metrics as fixed in LiDiff#45)",
    consumes=(SceneCompletionScoreCard.SCORES,),
)

__all__ = ["EMDScoreCard", "OccupancyScoreCard", "SSCScoreCard", "SceneCompletionScoreCard", "range_key"]
