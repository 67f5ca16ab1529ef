"""Cards of LiCROcc's distillation terms (Ma et al., RA-L 2025): PDD on the voxel logits, CMRD and BRD on
bird's-eye maps (:mod:`distilkit.objectives.licrocc`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective

MAX_MAPS = 3  # the release's three BEV scales
_EXTRA = [(f"student_{i}", f"teacher_{i}") for i in range(2, MAX_MAPS + 1)]
_PAPER = "LiCROcc (Ma et al., RA-L 2025, arXiv 2407.16197), ssc_rs.py"

AutoWeight = Literal["off", "release"]
_AUTO = ("off: the weight as given (the release: its distill_len = 0 leaves AutomaticWeightedLoss unbuilt); "
         "release: the term times 0.5 / sigma^2 with a learned sigma (initial 1) and no regulariser, as its class "
         "would compute (its log(1 + sigma^2) is commented out: sigma grows and the weight decays towards 0)")
_UNUSEFUL = ("the weight of a sample whose batch says `scene_useful: false` (the release's 1e-5 for night and rain "
             "scenes, never applied: its dataset calls every scene useful); 1: every sample alike")


class _Weights(BaseModel):
    model_config = ConfigDict(extra="forbid")
    unuseful_weight: float = Field(1.0, ge=0, description=_UNUSEFUL)
    auto_weight: AutoWeight = Field("off", description=_AUTO)


class KLParams(_Weights):
    pass


class BEVParams(_Weights):
    transpose_mask: bool = Field(False, description="apply the occupied-cell mask transposed, as the release's code "
                                                    "does ([x, y] mask on [y, x] features; square maps only)")


class AffinityParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: tuple[int, int] | None = Field((32, 32), description="each map resized (bilinear) to this (H, W) before "
                                                               "its affinity (the release: 32 x 32, its last map's); "
                                                               "null: as they are (P = H W cells, in tiles)")
    release_batch: bool = Field(False, description="divide each map's mean by the batch size again, as the release "
                                                   "(its weight is then 40 / B per sample)")
    auto_weight: AutoWeight = Field("off", description=_AUTO)


class KLCard(ObjectiveCard):
    """LiCROcc's PDD (card of :class:`distilkit.objectives.licrocc.PDD`), weight 10."""

    Params = KLParams
    MATCH = {"teacher": Match("equal", "same")}
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 10.0

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        return {"teacher": "occupied"}  # the KL at the voxels with a class label

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({"teacher"})


class BEVCard(ObjectiveCard):
    """LiCROcc's CMRD (card of :class:`distilkit.objectives.licrocc.CMRD`): up to three map pairs, weight 4."""

    Params = BEVParams
    MATCH = {role: Match("equal", "same", on_labels=True) for role in ("teacher", "teacher_2", "teacher_3")}
    CONSUMES = {"student": "bev_features", "teacher": "bev_features",
                **{role: "bev_features" for pair in _EXTRA for role in pair}}
    TEACHER_ROLES = frozenset({"teacher", *(t for _, t in _EXTRA)})
    OPTIONAL = frozenset(role for pair in _EXTRA for role in pair)
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 4.0  # its teacher maps are planes: a store keeps every cell (its masks are of voxels)


class AffinityCard(ObjectiveCard):
    """LiCROcc's BRD (card of :class:`distilkit.objectives.licrocc.BRD`): up to three map pairs, weight 40."""

    Params = AffinityParams
    MATCH = {role: Match("any", "resampled") for role in ("teacher", "teacher_2", "teacher_3")}

    @classmethod
    def match(cls, params: BaseModel | None = None) -> dict[str, Match]:
        """Both maps resized to ``size`` (any sizes); ``size: null`` compares them as they are: one size."""
        if params is not None and getattr(params, "size", 32) is None:
            return {role: Match("any", "same") for role in cls.MATCH}
        return cls.MATCH
    CONSUMES = BEVCard.CONSUMES
    TEACHER_ROLES = BEVCard.TEACHER_ROLES
    OPTIONAL = BEVCard.OPTIONAL
    DEFAULT_WEIGHT = 40.0


declare_objective("licrocc_kl", "distilkit.objectives.licrocc:PDD", KLCard,
                  description="LiCROcc's PDD: per-sample KLDivLoss mean over the voxels with a class label, scene "
                              "weights",
                  paper=_PAPER,
                  equation="mean_b w_b 1/(n_b K) Σ_{v labelled} Σ_k p_T (log p_T − log p_S)",
                  shapes="(B, K, X, Y, Z) logits, student and teacher")
declare_objective("licrocc_bev", "distilkit.objectives.licrocc:CMRD", BEVCard,
                  description="LiCROcc's CMRD: 1 − cos over the BEV cells of occupied columns, per sample and map",
                  paper=_PAPER,
                  equation="mean_m mean_b w_b mean_{cells over an occupied column} (1 − cos(f_S, f_T)); x4",
                  shapes="(B, C, X, Y) bird's-eye maps, each pair of one shape (up to 3 pairs)")
declare_objective("licrocc_affinity", "distilkit.objectives.licrocc:BRD", AffinityCard,
                  description="LiCROcc's BRD: L1 between each model's cosine self-affinity of its resized BEV maps",
                  paper=_PAPER,
                  equation="Σ_m mean_{b,i,j} |cos_S(i, j) − cos_T(i, j)| on maps resized to 32 × 32; x40",
                  shapes="(B, C_s / C_t, H, W) bird's-eye maps (up to 3 pairs)")

__all__ = ["MAX_MAPS", "AffinityCard", "AffinityParams", "BEVCard", "BEVParams", "KLCard", "KLParams"]
