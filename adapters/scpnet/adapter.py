"""How distilkit sees SCPNet: taps ``completion`` (sparse), ``completion_dense``, ``logits``."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.adapter import Adapter, select_frames
from distilkit.data.datasets import DataInfo
from distilkit.geometry.voxel import dense_to_sparse
from distilkit.registry import ADAPTERS
from distilkit_adapters.scpnet.model import SCPNet


class SCPNetParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frames: int = Field(1, ge=1, description="input scans fused (teacher: 4-5, student: 1)")
    channels: int = Field(32, ge=1, description="completion sub-network width (paper: 32)")
    point_mlp: list[int] = Field(default_factory=lambda: [64, 128], description="point MLP widths (paper: 64,128,256,256)")
    seg_channels: int = Field(32, ge=1, description="segmentation U-Net base width")


class SCPNetAdapter(Adapter):
    """SCPNet: MPB completion sub-network then segmentation; CE + Lovász task loss (eq. 4, alpha = 1)."""

    Params = SCPNetParams
    TAPS = {"completion": "sparse_features", "completion_dense": "feature_map", "logits": "voxel_logits"}
    LOGITS_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "ce", "weight": 1.0}, {"name": "lovasz", "weight": 1.0}]

    def __init__(self, params: SCPNetParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net = SCPNet(params.channels, params.point_mlp, params.seg_channels, info.num_classes)

    def forward(self, batch: dict[str, Tensor]) -> dict[str, Any]:
        b = select_frames(batch, self.params.frames)
        vox = self.net.voxelizer(b, self.info.grid, int(batch["voxel_label"].shape[0]))
        completed = self.net.completion(vox)
        logits = self.net.segmentation(completed)
        return {"completion": dense_to_sparse(completed), "completion_dense": completed, "logits": logits}


ADAPTERS.add("scpnet", SCPNetAdapter,
             description="SCPNet: multi-path-block completion sub-network + segmentation (dense U-Net stand-in)",
             paper="Xia et al., SCPNet, CVPR 2023", consumes=tuple(SCPNetAdapter.TAPS.values()))
