"""Class-centre objectives: RGO²D (Scribble2Scene) and its ancestor CleanerS."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from distilkit.cards.objectives.region import (FEATURE_ROLES, LOGITS_AND_OPTIONAL_FEATURES, CleanerSCard,
                                               CleanerSParams, RGO2DCard, RGO2DParams)
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.feature import fitnet
from distilkit.losses.cleaners import cleaners
from distilkit.losses.rgo2d import rgo2d
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.common import match_spatial, voxel_mask


def geometry(target: Tensor, ignore_index: int) -> Tensor:
    """The dense-geometry occupancy mask (target neither empty nor ``ignore_index``), as in the authors' code."""
    occupied = voxel_mask(target, "occupied", ignore_index)
    assert occupied is not None
    return occupied


def _feature_term(taps: dict[str, Any]) -> Tensor | None:
    if "student_features" not in taps:
        return None
    s, t = taps["student_features"], taps["teacher_features"]
    return fitnet(match_spatial(s, tuple(t.shape[2:])), t)


class RGO2D(RGO2DCard, MultiTapObjective):
    """RGO²D (Scribble2Scene, Wang et al. IJCAI 2024, eq. 2-4): range-guided global (GSL, DIST-style)
    and local (LSA) distillation, plus 0.6 x feature MSE when ``student_features``/``teacher_features``
    taps are given (image features in the paper)."""

    CHOICES = (
        Choice("class-centre labels", "the scribbles (a dataset without them is refused by validate)",
               "eq. 2-3: scribble labels", "utils/distillation_loss.py: the scribbles",
               "`taps: {labels: voxel_target}` (the dense labels, by name)"),
    )

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        p = self.params
        labels, occupied = taps["labels"], geometry(taps["target"], self.ignore_index)
        loss = rgo2d(taps["student"], taps["teacher"], labels, occupied, p.regions, p.region_weights, p.inter, p.intra,
                     self.ignore_index, p.local)
        feat = _feature_term(taps)
        return loss if feat is None else loss + p.feature_weight * feat


class CleanerS(CleanerSCard, MultiTapObjective):
    """CleanerS (Wang et al., CVPR 2023): KD-T (feature MSE), KD-SC (KL between softened class-centre
    logits of teacher and student) and KD-SA (MSE of voxel-to-centre cosine affinities); centres are
    class means over labelled voxels (classes != 0), as in the authors' code (seed_code.md §2.3).
    Default weight 0.25 as in their total loss."""

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        p = self.params
        sf, tf = taps.get("student_features"), taps.get("teacher_features")
        if sf is not None and tf is not None:
            sf = match_spatial(sf, tuple(tf.shape[2:]))
        return cleaners(taps["student"], taps["teacher"], taps["target"], p.temperature, p.kd_sc,
                        p.kd_sa, self.ignore_index, sf, tf, p.kd_t)


__all__ = ["FEATURE_ROLES", "LOGITS_AND_OPTIONAL_FEATURES", "CleanerS", "CleanerSParams", "RGO2D", "RGO2DParams",
           "geometry"]
