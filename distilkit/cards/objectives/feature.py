"""Cards of the feature objectives: FitNets, NST and MGD on dense feature maps (:mod:`distilkit.objectives.feature`)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective
from distilkit.cards.objectives.common import NoParams


class FitNetsCard(ObjectiveCard):
    """FitNets' hint (card of :class:`distilkit.objectives.feature.FitNets`)."""

    Params = NoParams
    MATCH = {"teacher": Match("own", "resampled")}  # its default linear connector projects
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 1.0
    DEFAULT_CONNECTOR = "linear"
    VERSION = 2  # 2: the regressor is a connector (same numbers, other checkpoint keys)


class NSTCard(ObjectiveCard):
    """NST (card of :class:`distilkit.objectives.feature.NST`)."""

    Params = NoParams
    MATCH = {"teacher": Match("any", "resampled")}  # both pooled to the smaller size
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 50.0


class MGDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mask_ratio: float = Field(0.65, ge=0, lt=1, description="lambda: fraction of positions masked (MGD: 0.65 dense)")


class MGDCard(ObjectiveCard):
    """MGD (card of :class:`distilkit.objectives.feature.MGD`)."""

    Params = MGDParams
    MATCH = {"teacher": Match("own", "resampled")}  # its 1x1 ``align`` where the widths differ
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 1.0


declare_objective("fitnets", "distilkit.objectives.feature:FitNets", FitNetsCard,
                  description="FitNets hint: MSE after a learnable 1x1 regressor (2-D or 3-D)",
                  paper="Romero et al., ICLR 2015; SCPNet Table 4", equation="mean (r(F_s) − F_t)²",
                  shapes="(B, C_s, *S) and (B, C_t, *S') feature maps; r: 1×1 conv C_s → C_t", function="fitnet")
declare_objective("nst", "distilkit.objectives.feature:NST", NSTCard,
                  description="NST: squared MMD (polynomial kernel) between channel-response distributions",
                  paper="Huang & Wang, arXiv 2017 (Neuron Selectivity Transfer); SCPNet Table 4",
                  equation="mean k(T,T) + mean k(S,S) − 2 mean k(S,T), k(a,b) = (aᵀb)²",
                  shapes="(B, C_s, *S), (B, C_t, *S); the larger map is pooled to the smaller")
declare_objective("mgd", "distilkit.objectives.feature:MGD", MGDCard,
                  description="MGD: reconstruct the teacher's features from randomly masked student features",
                  paper="Yang et al., ECCV 2022; Scribble2Scene Table 5",
                  equation="mean (G(align(F_s) ⊙ M) − F_t)², M ~ Bernoulli(1 − λ)",
                  shapes="(B, C_s, *S), (B, C_t, *S) feature maps")

__all__ = ["FitNetsCard", "MGDCard", "MGDParams", "NSTCard", "NoParams"]
