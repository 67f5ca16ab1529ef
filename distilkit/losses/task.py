"""Registered task losses (supervised terms of a stage): CE, Lovász-softmax, uncertainty weighting."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.data.classes import IGNORE_INDEX
from distilkit.losses.segmentation import cross_entropy, lovasz_softmax
from distilkit.registry import TASK_LOSSES


class TaskLoss(nn.Module, ABC):
    """A supervised term: ``forward(outputs, batch) -> scalar``. ``CONSUMES`` lists tap kinds it reads."""

    Params: ClassVar[type[BaseModel]]
    CONSUMES: ClassVar[dict[str, str]] = {"student": "voxel_logits"}
    VERSION: ClassVar[int] = 1  # bump when the loss's numbers change: stages using it retrain

    def __init__(self, params: BaseModel, taps: dict[str, str]) -> None:
        super().__init__()
        self.params = params
        self.taps = taps  # role -> tap name on the model

    @abstractmethod
    def forward(self, outputs: dict[str, Any], batch: dict[str, Tensor]) -> Tensor:
        """The scalar loss of the model's ``outputs`` on ``batch``."""


class _CEParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ignore_index: int = IGNORE_INDEX


class VoxelCE(TaskLoss):
    """Cross entropy on voxel logits against ``voxel_target`` (invalid voxels ignored)."""

    Params = _CEParams

    def forward(self, outputs: dict[str, Any], batch: dict[str, Tensor]) -> Tensor:
        return cross_entropy(outputs[self.taps["student"]], batch["voxel_target"], self.params.ignore_index)


class _LovaszParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    classes: str = Field("present", pattern="^(present|all)$")
    ignore_index: int = IGNORE_INDEX


class VoxelLovasz(TaskLoss):
    """Lovász-softmax on voxel logits (SCPNet eq. 4, alpha term)."""

    Params = _LovaszParams

    def forward(self, outputs: dict[str, Any], batch: dict[str, Tensor]) -> Tensor:
        return lovasz_softmax(outputs[self.taps["student"]], batch["voxel_target"], self.params.ignore_index,
                              self.params.classes)


class _UncParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    init_log_var: float = Field(0.0, description="initial s = log sigma^2 of both tasks")


class UncertaintyMultiTask(TaskLoss):
    """JS3C-Net eq. 2 (Kendall et al. 2018): L = sum_i 1/(2 sigma_i^2) L_i + log sigma_i.

    Parametrised by s_i = log sigma_i^2 (always finite, unlike the authors' raw sigma, seed_code.md §4):
    L = sum_i 0.5 * exp(-s_i) * L_i + 0.5 * s_i, over L_seg (point CE, unlabelled points ignored) and
    L_complet (voxel CE, invalid voxels ignored). The s_i are trained with the student.
    """

    Params = _UncParams
    CONSUMES = {"student": "voxel_logits", "points": "point_logits"}

    def __init__(self, params: _UncParams, taps: dict[str, str]) -> None:
        super().__init__(params, taps)
        self.log_var = nn.Parameter(torch.full((2,), float(params.init_log_var)))

    def forward(self, outputs: dict[str, Any], batch: dict[str, Tensor]) -> Tensor:
        # adapters whose point logits cover a subset of the batch's points return their targets
        labels = outputs.get("point_target", batch["point_label"])
        seg_target = labels.masked_fill(labels == 0, IGNORE_INDEX)
        l_seg = cross_entropy(outputs[self.taps["points"]], seg_target)
        l_comp = cross_entropy(outputs[self.taps["student"]], batch["voxel_target"])
        s = self.log_var
        return 0.5 * torch.exp(-s[0]) * l_seg + 0.5 * s[0] + 0.5 * torch.exp(-s[1]) * l_comp + 0.5 * s[1]


TASK_LOSSES.add("ce", VoxelCE, description="voxel cross entropy, ignore 255 and invalid voxels",
                paper="SCPNet eq. 4 (L_ce)", consumes=("voxel_logits",))
TASK_LOSSES.add("lovasz", VoxelLovasz, description="Lovász-softmax over classes present in the batch",
                paper="Berman et al. CVPR 2018; SCPNet eq. 4 (alpha = 1)", consumes=("voxel_logits",))
TASK_LOSSES.add("uncertainty_multitask", UncertaintyMultiTask,
                description="uncertainty-weighted point segmentation + completion CE (log-variance form)",
                paper="JS3C-Net eq. 2 (Kendall et al. CVPR 2018)", consumes=("voxel_logits", "point_logits"))
