"""Cards of the class-centre objectives: RGO²D (Scribble2Scene) and CleanerS (:mod:`distilkit.objectives.region`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective

# logits of both models, plus an optional feature pair (image features in Scribble2Scene)
LOGITS_AND_OPTIONAL_FEATURES = {"student": "voxel_logits", "teacher": "voxel_logits",
                                "student_features": "feature_map", "teacher_features": "feature_map"}
FEATURE_ROLES = frozenset({"student_features", "teacher_features"})
# the feature term is FitNets' MSE after the student is resized, with no connector on its role: equal widths
LOGITS_AND_FEATURES_MATCH = {"teacher": Match("equal", "same"), "teacher_features": Match("equal", "resampled")}


class RGO2DParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    regions: Literal["boxes", "rings"] = Field("boxes", description="nested boxes (authors' code) or radial rings")
    region_weights: tuple[float, float, float] = (0.06, 0.15, 0.20)
    inter: float = 2.625
    intra: float = 0.375
    local: float = Field(1.0, ge=0, description="weight of the local (affinity) term in each region (Table 6 "
                                                "ablations: 0 = global only; inter = intra = 0: local only)")
    feature_weight: float = Field(0.6, ge=0, description="weight of the image-feature MSE (with feature taps)")


class RGO2DCard(ObjectiveCard):
    """RGO²D (card of :class:`distilkit.objectives.region.RGO2D`)."""

    Params = RGO2DParams
    MATCH = LOGITS_AND_FEATURES_MATCH
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

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # the logits' rows are gathered at the target's occupied voxels; the feature MSE reads the whole map
        return {"teacher": "occupied", "teacher_features": "all"}


class CleanerSParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    kd_t: float = Field(1.0, ge=0, description="feature MSE (with feature taps)")
    kd_sc: float = Field(1.0, ge=0, description="semantic-centre KL")
    kd_sa: float = Field(1.0, ge=0, description="semantic-affinity MSE")


class CleanerSCard(ObjectiveCard):
    """CleanerS (card of :class:`distilkit.objectives.region.CleanerS`); default weight 0.25."""

    Params = CleanerSParams
    MATCH = LOGITS_AND_FEATURES_MATCH
    CONSUMES = LOGITS_AND_OPTIONAL_FEATURES
    TEACHER_ROLES = frozenset({"teacher", "teacher_features"})
    OPTIONAL = FEATURE_ROLES
    BATCH = {"target": "voxel_target"}  # the labels of the class centres
    DEFAULT_WEIGHT = 0.25

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        # centres and affinities over the non-ignored voxels (empty ones too); the feature MSE reads the whole map
        return {"teacher": "valid", "teacher_features": "all"}


declare_objective("rgo2d", "distilkit.objectives.region:RGO2D", RGO2DCard,
                  description="RGO²D: range-guided global (class-centre DIST) + local (affinity) distillation",
                  paper="Scribble2Scene (Wang et al., IJCAI 2024), eq. 2-4",
                  equation="Σ_r w_r (2.625 inter_r + 0.375 intra_r + LSA_r) + 0.6 · MSE(F_s, F_t)",
                  shapes="(B, K, X, Y, Z) logits; labels and dense-geometry mask from the batch")
declare_objective("cleaners", "distilkit.objectives.region:CleanerS", CleanerSCard,
                  description="CleanerS: feature, semantic-centre KL and semantic-affinity distillation",
                  paper="Wang et al., CVPR 2023 (CleanerS); Scribble2Scene Table 5",
                  equation="KD-T + T² mean_c KL(σ(G_t/T) ‖ σ(G_s/T)) + MSE(cos(y_s, G_s), cos(y_t, G_t))",
                  shapes="(B, K, X, Y, Z) logits (+ optional feature maps)")

__all__ = ["FEATURE_ROLES", "LOGITS_AND_OPTIONAL_FEATURES", "CleanerSCard", "CleanerSParams", "RGO2DCard",
           "RGO2DParams"]
