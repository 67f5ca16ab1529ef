"""Class-centre objectives: RGO²D (Scribble2Scene) and its ancestor CleanerS."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.feature import fitnet
from distilkit.losses.cleaners import cleaners
from distilkit.losses.rgo2d import rgo2d
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.common import match_spatial, voxel_mask


# logits of both models, plus an optional feature pair (image features in Scribble2Scene)
LOGITS_AND_OPTIONAL_FEATURES = {"student": "voxel_logits", "teacher": "voxel_logits",
                                "student_features": "feature_map", "teacher_features": "feature_map"}
FEATURE_ROLES = frozenset({"student_features", "teacher_features"})


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


class RGO2DParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    regions: Literal["boxes", "rings"] = Field("boxes", description="nested boxes (authors' code) or radial rings")
    region_weights: tuple[float, float, float] = (0.06, 0.15, 0.20)
    inter: float = 2.625
    intra: float = 0.375
    local: float = Field(1.0, ge=0, description="weight of the local (affinity) term in each region (Table 6 "
                                                "ablations: 0 = global only; inter = intra = 0: local only)")
    feature_weight: float = Field(0.6, ge=0, description="weight of the image-feature MSE (with feature taps)")


class RGO2D(MultiTapObjective):
    """RGO²D (Scribble2Scene, Wang et al. IJCAI 2024, eq. 2-4): range-guided global (GSL, DIST-style)
    and local (LSA) distillation, plus 0.6 x feature MSE when ``student_features``/``teacher_features``
    taps are given (image features in the paper)."""

    CHOICES = (
        Choice("class-centre labels", "the scribbles (a dataset without them is refused by validate)",
               "eq. 2-3: scribble labels", "utils/distillation_loss.py: the scribbles",
               "`taps: {labels: voxel_target}` (the dense labels, by name)"),
    )

    Params = RGO2DParams
    CONSUMES = LOGITS_AND_OPTIONAL_FEATURES
    TEACHER_ROLES = frozenset({"teacher", "teacher_features"})
    OPTIONAL = FEATURE_ROLES
    # the sparse labels of the class centres (the scribbles: never silently the dense labels) and the dense target
    # that gives the geometry
    BATCH = {"labels": "scribble", "target": "voxel_target"}
    BATCH_HINTS = {"labels": "RGO²D's class centres come from scribbles (semantickitti-ssc reads ScribbleSC's with "
                             "`scribbles: FOLDER`); to use the dense labels instead, say so: `taps: {labels: "
                             "voxel_target}`"}
    DEFAULT_WEIGHT = 1.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        p = self.params
        labels, occupied = taps["labels"], geometry(taps["target"], self.ignore_index)
        loss = rgo2d(taps["student"], taps["teacher"], labels, occupied, p.regions, p.region_weights, p.inter, p.intra,
                     self.ignore_index, p.local)
        feat = _feature_term(taps)
        return loss if feat is None else loss + p.feature_weight * feat


class CleanerSParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    kd_t: float = Field(1.0, ge=0, description="feature MSE (with feature taps)")
    kd_sc: float = Field(1.0, ge=0, description="semantic-centre KL")
    kd_sa: float = Field(1.0, ge=0, description="semantic-affinity MSE")


class CleanerS(MultiTapObjective):
    """CleanerS (Wang et al., CVPR 2023): KD-T (feature MSE), KD-SC (KL between softened class-centre
    logits of teacher and student) and KD-SA (MSE of voxel-to-centre cosine affinities); centres are
    class means over labelled voxels (classes != 0), as in the authors' code (seed_code.md §2.3).
    Default weight 0.25 as in their total loss."""

    Params = CleanerSParams
    CONSUMES = LOGITS_AND_OPTIONAL_FEATURES
    TEACHER_ROLES = frozenset({"teacher", "teacher_features"})
    OPTIONAL = FEATURE_ROLES
    BATCH = {"target": "voxel_target"}  # the labels of the class centres
    DEFAULT_WEIGHT = 0.25

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        p = self.params
        sf, tf = taps.get("student_features"), taps.get("teacher_features")
        if sf is not None and tf is not None:
            sf = match_spatial(sf, tuple(tf.shape[2:]))
        return cleaners(taps["student"], taps["teacher"], taps["target"], p.temperature, p.kd_sc,
                        p.kd_sa, self.ignore_index, sf, tf, p.kd_t)


register_objective("rgo2d", RGO2D, description="RGO²D: range-guided global (class-centre DIST) + local (affinity) distillation",
               paper="Scribble2Scene (Wang et al., IJCAI 2024), eq. 2-4",
               equation="Σ_r w_r (2.625 inter_r + 0.375 intra_r + LSA_r) + 0.6 · MSE(F_s, F_t)",
               shapes="(B, K, X, Y, Z) logits; labels and dense-geometry mask from the batch")
register_objective("cleaners", CleanerS, description="CleanerS: feature, semantic-centre KL and semantic-affinity distillation",
               paper="Wang et al., CVPR 2023 (CleanerS); Scribble2Scene Table 5",
               equation="KD-T + T² mean_c KL(σ(G_t/T) ‖ σ(G_s/T)) + MSE(cos(y_s, G_s), cos(y_t, G_t))",
               shapes="(B, K, X, Y, Z) logits (+ optional feature maps)")
