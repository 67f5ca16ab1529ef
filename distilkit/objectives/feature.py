"""Feature objectives: FitNets, NST and MGD on dense feature maps (2-D or 3-D)."""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn

from distilkit.cards.objectives.feature import FitNetsCard, MGDCard, MGDParams, NoParams, NSTCard
from distilkit.data.batch import Batch
from distilkit.losses.feature import fitnet, nst
from distilkit.losses.mgd import mgd
from distilkit.objectives.base import Objective
from distilkit.objectives.common import conv1x1, match_spatial


class FitNets(FitNetsCard, Objective):
    """FitNets (Romero et al., ICLR 2015): MSE between a learnable 1x1 regression of the student's
    features and the teacher's. The regressor is the ``linear`` connector (Conv2d or Conv3d, sized from
    the first batch, trained with the student); the student map is resampled to the teacher's spatial
    size if needed."""

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        return fitnet(match_spatial(student, tuple(teacher.shape[2:])), teacher)


class NST(NSTCard, Objective):
    """NST (Huang & Wang 2017): polynomial-kernel MMD of spatially normalised channel responses."""

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        shape = tuple(min(a, b) for a, b in zip(student.shape[2:], teacher.shape[2:]))
        return nst(match_spatial(student, shape), match_spatial(teacher, shape))


class MGD(MGDCard, Objective):
    """MGD (Yang et al., ECCV 2022): mask random positions of the (aligned) student
    map and let a generator (conv3-ReLU-conv3) reconstruct the teacher's full map; MSE (mean over elements)."""

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        s, t = taps["student"], taps["teacher"]
        dims, c = s.dim() - 2, t.shape[1]
        conv = nn.Conv3d if dims == 3 else nn.Conv2d
        self.align = conv1x1(s.shape[1], c, dims) if s.shape[1] != c else nn.Identity()
        self.generator = nn.Sequential(conv(c, c, 3, padding=1), nn.ReLU(inplace=True), conv(c, c, 3, padding=1))

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        return mgd(match_spatial(self.align(student), tuple(teacher.shape[2:])), teacher, self.generator,
                   self.params.mask_ratio)


__all__ = ["MGD", "NST", "FitNets", "MGDParams", "NoParams"]
