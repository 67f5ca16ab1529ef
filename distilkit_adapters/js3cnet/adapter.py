"""How distilkit sees JS3C-Net: taps ``logits``, ``point_logits`` (+ their ``point_target``), ``completion``
(sparse), ``ssc_dense``."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.data.lidar import select_frames
from distilkit.structures import VoxelGrid
from distilkit.registry import ADAPTERS
from distilkit.structures import SparseVoxels
from distilkit_adapters._blocks import MultiFrameLidarAdapter, channels_last
from distilkit_adapters.js3cnet.model import JS3CNet


class JS3CNetParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    frames: int = Field(1, ge=1, description="input scans fused (SCPNet appendix: multi-frame teacher)")
    seg_channels: int = Field(16, ge=1, description="segmentation U-Net width (paper: m = 16)")
    embed: int = Field(16, ge=1, description="shape-embedding width D_e")
    ssc_channels: int = Field(32, ge=1, description="SSC decoder width (paper: 32)")
    pvi_hidden: int = Field(32, ge=1, description="PVI MLP width (paper: 32)")
    knn: int = Field(8, ge=1, description="neighbours per query in the PVI (paper code: 8)")


class JS3CNetAdapter(MultiFrameLidarAdapter):
    """JS3C-Net with the uncertainty-weighted multi-task loss (eq. 2) as its task loss. Its choices against the paper
    and the release (``CHOICES``): 3 SSC decoder blocks, segmentation on the 0.2 m grid, a residual refinement."""

    CHOICES = (
        Choice("SSC decoder blocks", "3 residual blocks (the last two dilated by 2)",
               "supplement: five basic blocks of 32 channels", "SSCNet_Decoder: 5 blocks", "`ssc_channels` sets the width only"),
        Choice("segmentation resolution", "a dense U-Net on the 0.2 m completion grid (CPU-sized)",
               "§4: 0.05 m grids for the SparseConv U-Net", "JS3C_default_kitti.yaml: 0.1 m (scale 10)",
               ""),
        Choice("PVI refinement", "residual: FC([aggregated, coarse logits]) added to the coarse logits",
               "Fig. 3: the PVI output replaces the coarse completion", "FC(m + 20 -> 20) replaces them; a final ReLU "
               "on the logits (left out here)"),
    )

    Params = JS3CNetParams
    TAPS = {"completion": "sparse_features", "ssc_dense": "volume_features", "logits": "voxel_logits",
            "point_logits": "point_logits", "point_target": "point_labels"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "uncertainty_multitask", "weight": 1.0}]
    VERSION = 2  # 2: channels-last volumes

    def __init__(self, params: JS3CNetParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net = JS3CNet(info.grid, info.num_classes, params.seg_channels, params.embed, params.ssc_channels,
                           params.pvi_hidden, params.knn)
        channels_last(self)

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        if tap == "completion" and info.grid is not None:  # the SSC decoder works at half resolution
            return info.grid.coarsen(2)
        return super().tap_grid(tap, params, info)

    def forward(self, batch: Batch) -> dict[str, Any]:
        b = select_frames(batch, self.params.frames)
        out = self.net(b.inputs, batch.size)
        shape = tuple(out["ssc_dense"].shape[2:])
        return {
            "logits": out["logits"],
            # point logits of the *current* scan's points, aligned with batch["point_label"] of frame 0
            "point_logits": out["point_logits"],
            "completion": SparseVoxels(out["ssc_coords"], out["ssc_feats"], shape,  # type: ignore[arg-type]
                                       self.tap_grid("completion", self.params, self.info)),
            "ssc_dense": out["ssc_dense"],
            # segmentation targets of the points behind point_logits (input points inside the grid)
            "point_target": b.targets["point_label"][out["point_keep"]],
        }


ADAPTERS.add("js3cnet", JS3CNetAdapter,
             description="JS3C-Net: segmentation branch, SSC decoder and point-voxel interaction (dense CPU variant)",
             paper="Yan et al., JS3C-Net, AAAI 2021", consumes=tuple(JS3CNetAdapter.TAPS.values()))
