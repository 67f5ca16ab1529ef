"""Feature objectives: FitNets, NST and MGD on dense feature maps (2-D or 3-D)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.data.batch import Batch
from distilkit.losses.feature import fitnet, nst
from distilkit.losses.mgd import mgd
from distilkit.objectives.base import Objective, register_objective
from distilkit.objectives.common import conv1x1, match_spatial


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FitNets(Objective):
    """FitNets (Romero et al., ICLR 2015): MSE between a learnable 1x1 regression of the student's
    features and the teacher's. The regressor is the ``linear`` connector (Conv2d or Conv3d, sized from
    the first batch, trained with the student); the student map is resampled to the teacher's spatial
    size if needed."""

    Params = NoParams
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 1.0
    DEFAULT_CONNECTOR = "linear"
    VERSION = 2  # 2: the regressor is a connector (same numbers, other checkpoint keys)

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        return fitnet(match_spatial(student, tuple(teacher.shape[2:])), teacher)


class NST(Objective):
    """NST (Huang & Wang 2017): polynomial-kernel MMD of spatially normalised channel responses."""

    Params = NoParams
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 50.0

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        shape = tuple(min(a, b) for a, b in zip(student.shape[2:], teacher.shape[2:]))
        return nst(match_spatial(student, shape), match_spatial(teacher, shape))


class MGDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    mask_ratio: float = Field(0.65, ge=0, lt=1, description="lambda: fraction of positions masked (MGD: 0.65 dense)")


class MGD(Objective):
    """MGD (Yang et al., ECCV 2022): mask random positions of the (aligned) student
    map and let a generator (conv3-ReLU-conv3) reconstruct the teacher's full map; MSE (mean over elements)."""

    Params = MGDParams
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 1.0

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        s, t = taps["student"], taps["teacher"]
        dims, c = s.dim() - 2, t.shape[1]
        conv = nn.Conv3d if dims == 3 else nn.Conv2d
        self.align = conv1x1(s.shape[1], c, dims) if s.shape[1] != c else nn.Identity()
        self.generator = nn.Sequential(conv(c, c, 3, padding=1), nn.ReLU(inplace=True), conv(c, c, 3, padding=1))

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        return mgd(match_spatial(self.align(student), tuple(teacher.shape[2:])), teacher, self.generator,
                   self.params.mask_ratio)


register_objective("fitnets", FitNets, description="FitNets hint: MSE after a learnable 1x1 regressor (2-D or 3-D)",
               paper="Romero et al., ICLR 2015; SCPNet Table 4", equation="mean (r(F_s) − F_t)²",
               shapes="(B, C_s, *S) and (B, C_t, *S') feature maps; r: 1×1 conv C_s → C_t", function="fitnet")
register_objective("nst", NST, description="NST: squared MMD (polynomial kernel) between channel-response distributions",
               paper="Huang & Wang, arXiv 2017 (Neuron Selectivity Transfer); SCPNet Table 4", equation="mean k(T,T) + mean k(S,S) − 2 mean k(S,T), k(a,b) = (aᵀb)²",
               shapes="(B, C_s, *S), (B, C_t, *S); the larger map is pooled to the smaller")
register_objective("mgd", MGD, description="MGD: reconstruct the teacher's features from randomly masked student features",
               paper="Yang et al., ECCV 2022; Scribble2Scene Table 5", equation="mean (G(align(F_s) ⊙ M) − F_t)², M ~ Bernoulli(1 − λ)",
               shapes="(B, C_s, *S), (B, C_t, *S) feature maps")
