"""The Dean-Labeler's card (torch-free): its parameters, taps and what ``validate`` asks of it; the network is
:mod:`distilkit_adapters.dean.adapter`'s."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from distilkit.cards.base import AdapterCard
from distilkit.data.info import DataInfo
from distilkit.registry import ADAPTERS
from distilkit.structures import VoxelGrid
from distilkit_adapters._cards import fields_of_one_size

Features = Literal["occupancy", "height", "position"]


class DeanParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field(
        "tiny", description="tiny: the CPU stand-in (a dense U-Net of `channels`); paper: the paper's Cylinder3D "
                            "(its asymmetric sparse U-Net at 32 channels, the SCPNet adapter's, on the occupied "
                            "voxels; the grid divisible by 16 x 16 x 4)")
    channels: int = Field(16, ge=1, description="size tiny: U-Net base width (size paper: Cylinder3D's 32)")
    features: Features = Field(
        "height", description="each occupied voxel's input: occupancy (a 1: the binary geometry alone), height (a 1 "
                              "and z scaled to [-1, 1]), position (a 1 and x, y, z scaled to [-1, 1])")
    semantics: Literal["spconv1", "spconv2"] = Field(
        "spconv1", description="size paper: spconv1 = Cylinder3D's release (spconv 1.2.1: a block's convolutions "
                               "share one indice_key and run on the first one's neighbourhood), spconv2 = its spconv "
                               "2.x ports (a key per convolution, every kernel as written)")
    geometry: str = Field("voxel_target", description="the batch field whose occupied voxels (neither empty nor "
                                                      "ignored) are the complete geometry")

    @model_validator(mode="after")
    def _one_size(self) -> "DeanParams":
        fields_of_one_size(self, {"tiny": ("channels",), "paper": ("semantics",)})
        return self


class DeanLabelerCard(AdapterCard):
    """The Dean-Labeler's declarations (the adapter: :class:`distilkit_adapters.dean.adapter.DeanLabelerAdapter`)."""

    Params = DeanParams
    NETWORKS = {"tiny": "CPU stand-in: the dense U-Net the LiDAR adapters share (the paper's is Cylinder3D)",
                "paper": "the paper's network: Cylinder3D's asymmetric sparse U-Net (the SCPNet adapter's, without "
                         "its completion sub-network) on the complete geometry's occupied voxels"}
    TAPS = {"features": "volume_features", "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "partial_ce", "weight": 1.0, "params": {"class_weights": "none"}}]
    VERSION = 2  # 2: size paper (Cylinder3D), input features as a parameter (tiny's default unchanged)

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({getattr(params, "geometry")})

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        """The U-Net's last features live on the data's grid, as its logits do."""
        if tap == "features":
            return info.grid
        return super().tap_grid(tap, params, info)

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        grid = info.grid
        if getattr(params, "size") == "paper" and grid is not None and (
                grid.shape[0] % 16 or grid.shape[1] % 16 or grid.shape[2] % 4):
            return [("size", f"Cylinder3D's U-Net pools x and y four times and z twice: the grid {grid.shape} must "
                             "be divisible by 16 x 16 x 4 (SemanticKITTI's 256 x 256 x 32 at scale 1, 2 or 4)")]
        return []

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """The paper's network (``size: paper``) runs sparse convolutions (distilkit.sparse); the stand-in none."""
        return getattr(params, "size") == "paper"

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return "complete geometry" + (", paper size" if getattr(params, "size") == "paper" else "")


ADAPTERS.declare("dean-labeler", "distilkit_adapters.dean.adapter:DeanLabelerAdapter", card=DeanLabelerCard,
                 description="Scribble2Scene's Dean-Labeler: voxel segmentation of the complete geometry (partial CE "
                             "on scribbles; size paper: Cylinder3D); its published predictions are pseudo-labels",
                 paper="Wang et al., Scribble2Scene, IJCAI 2024 (§4.2, eq. 1; §5.1: Cylinder3D, batch 4)",
                 consumes=tuple(DeanLabelerCard.TAPS.values()))
