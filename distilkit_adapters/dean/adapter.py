"""How distilkit sees Scribble2Scene's Dean-Labeler (Wang et al. IJCAI 2024, §4.2, eq. 1).

The Dean-Labeler takes the complete geometry as input, so scene completion becomes voxel segmentation: a 3-D U-Net
(the paper's Cylinder3D; here the dense CPU-sized U-Net the LiDAR adapters share) reads each voxel's occupancy and
height and labels every occupied voxel with a class; empty voxels stay empty (the network does not change the
geometry: IoU 100 %, Table 3). Trained with partial CE on the scribbles (non-empty, labelled voxels only); its
predictions, published, become the camera student's labels (``labels: {from: dean, keep: scribble}``).
"""

from __future__ import annotations

from typing import Any

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.registry import ADAPTERS
from distilkit_adapters._blocks import DenseUNet3d, channels_last

EMPTY_LOGIT = 10.0  # class 0's logit outside the geometry; inside it, -EMPTY_LOGIT (a class is always chosen)


class DeanParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    channels: int = Field(16, ge=1, description="U-Net base width")
    geometry: str = Field("voxel_target", description="the batch field whose occupied voxels (neither empty nor "
                                                      "ignored) are the complete geometry")


def geometry_logits(logits: Tensor, occupied: Tensor) -> Tensor:
    """Class scores that keep the geometry: outside ``occupied`` (B, X, Y, Z) the constant "empty" vector, inside it
    the network's scores with class 0 held far below (no gradient through either constant)."""
    inside = logits.clone()
    inside[:, 0] = -EMPTY_LOGIT
    empty = torch.zeros(logits.shape[1], dtype=logits.dtype, device=logits.device)
    empty[0] = EMPTY_LOGIT
    return torch.where(occupied.unsqueeze(1), inside, empty.view(1, -1, 1, 1, 1))


class DeanLabelerAdapter(Adapter):
    """Voxel segmentation of the complete geometry; taps ``features`` (volume) and ``logits``."""

    Params = DeanParams
    NETWORKS = {"": "CPU stand-in: the dense U-Net the LiDAR adapters share (the paper's is Cylinder3D)"}
    TAPS = {"features": "volume_features", "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "partial_ce", "weight": 1.0, "params": {"class_weights": "none"}}]

    def __init__(self, params: DeanParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net = DenseUNet3d(2, params.channels, params.channels)
        self.head = torch.nn.Conv3d(params.channels, info.num_classes, 1)
        channels_last(self)

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({getattr(params, "geometry")})

    def forward(self, batch: Batch) -> dict[str, Any]:
        target = batch.field(self.params.geometry)
        occupied = (target != 0) & (target != self.info.classes.ignore_index)
        height = torch.linspace(-1.0, 1.0, target.shape[-1], device=target.device).expand(target.shape)
        x = torch.stack([occupied.float(), height * occupied], 1).contiguous(memory_format=torch.channels_last_3d)
        features = self.net(x)
        return {"features": features, "logits": geometry_logits(self.head(features), occupied)}

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return "complete geometry"


ADAPTERS.add("dean-labeler", DeanLabelerAdapter,
             description="Scribble2Scene's Dean-Labeler: voxel segmentation of the complete geometry (partial CE on "
                         "scribbles); its published predictions are pseudo-labels",
             paper="Wang et al., Scribble2Scene, IJCAI 2024 (§4.2, eq. 1)",
             consumes=tuple(DeanLabelerAdapter.TAPS.values()))
