"""JS3C-Net's card (torch-free): its parameters, taps and what ``validate`` asks of it; the network is
:mod:`distilkit_adapters.js3cnet.adapter`'s."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from distilkit.data.info import DataInfo
from distilkit.registry import ADAPTERS
from distilkit.structures import VoxelGrid
from distilkit_adapters._cards import MultiFrameLidarCard, fields_of_one_size


class JS3CNetParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field(
        "tiny", description="tiny: the CPU stand-in (a dense U-Net on the completion grid, the fields below); paper: "
                            "the release's network (args.txt of its checkpoint) — SparseConvNet's residual U-Net of "
                            "`levels` levels on seg_voxel voxels on distilkit.sparse, SSCNet's decoder, the "
                            "point-voxel interaction — with m = seg_channels, the decoder's width ssc_channels; "
                            "embed and pvi_hidden are m there; loads the release's checkpoint")
    levels: int = Field(7, ge=2, le=8, description="paper size: U-Net levels, widths m, 2m, ... (release: 7)")
    fuse_k: int = Field(5, ge=1, description="paper size: points averaged per completion voxel (release: first 5)")
    pvi_queries: Literal["all", "near"] = Field(
        "all", description="paper size: coarse voxels that query neighbours in the PVI — all: every non-zero one "
                           "(the release); near: occupied or next to an occupied one, every one fused (faster)")
    seg_voxel: float = Field(0.05, gt=0, description="paper size: the segmentation U-Net's voxel in metres (the "
                                                     "release's scale 20 and the paper: 0.05)")
    z_offset: int = Field(1, ge=0, description="paper size: added to each point's completion voxel z index before "
                                               "pooling (the release: 1, 'SemanticKITTI will generate "
                                               "[256,256,31]'; 0: the points' own voxels)")
    frames: int = Field(1, ge=1, description="input scans fused (SCPNet appendix: multi-frame teacher)")
    seg_channels: int = Field(16, ge=1, description="segmentation U-Net width (paper: m = 16)")
    embed: int = Field(16, ge=1, description="shape-embedding width D_e")
    ssc_channels: int = Field(32, ge=1, description="SSC decoder width (paper: 32)")
    pvi_hidden: int = Field(32, ge=1, description="PVI MLP width (paper: 32)")
    knn: int = Field(8, ge=1, description="neighbours per query in the PVI (paper code: 8)")

    @model_validator(mode="after")
    def _one_size(self) -> "JS3CNetParams":
        fields_of_one_size(self, {"tiny": ("embed", "pvi_hidden"),
                                  "paper": ("levels", "fuse_k", "pvi_queries", "seg_voxel", "z_offset")})
        return self


class JS3CNetCard(MultiFrameLidarCard):
    """JS3C-Net's declarations (the adapter: :class:`distilkit_adapters.js3cnet.adapter.JS3CNetAdapter`)."""

    Params = JS3CNetParams
    TAPS = {"completion": "sparse_features", "ssc_dense": "volume_features", "logits": "voxel_logits",
            "point_logits": "point_logits", "point_target": "point_labels"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "uncertainty_multitask", "weight": 1.0}]
    VERSION = 3  # 3: size paper as released (SparseConvNet); 2: channels-last volumes
    NETWORKS = {"tiny": "CPU stand-in: a dense U-Net on the completion grid, a 3-block SSC decoder, a residual PVI",
                "paper": "the paper's network as released: SparseConvNet's 7-level residual U-Net at 0.05 m, "
                         "SSCNet's decoder, the point-voxel interaction (loads the release's checkpoint)"}

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        if tap in ("completion", "ssc_dense") and info.grid is not None:  # the SSC decoder works at half resolution
            return info.grid.coarsen(2)
        return super().tap_grid(tap, params, info)

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """The paper's network (``size: paper``) runs sparse convolutions (distilkit.sparse); the stand-in none."""
        return getattr(params, "size") == "paper"

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return super().describe(params) + (", paper size" if getattr(params, "size") == "paper" else "")


ADAPTERS.declare("js3cnet", "distilkit_adapters.js3cnet.adapter:JS3CNetAdapter", card=JS3CNetCard,
                 description="JS3C-Net: segmentation branch, SSC decoder and point-voxel interaction (size: tiny, a "
                             "dense CPU stand-in; size: paper, the release's sparse U-Net)",
                 paper="Yan et al., JS3C-Net, AAAI 2021", consumes=tuple(JS3CNetCard.TAPS.values()))
