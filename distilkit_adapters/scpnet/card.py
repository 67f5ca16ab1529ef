"""SCPNet's card (torch-free): its parameters, taps and what ``validate`` asks of it; the network is
:mod:`distilkit_adapters.scpnet.adapter`'s."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from distilkit.data.info import DataInfo
from distilkit.registry import ADAPTERS
from distilkit.structures import VoxelGrid
from distilkit_adapters._cards import MultiFrameLidarCard, fields_of_one_size


class SCPNetParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field(
        "tiny", description="tiny: the CPU stand-in (the paper's three-branch completion, a dense U-Net for "
                            "segmentation; the fields below but frames); paper: the release's network — its "
                            "completion sub-network (dense) and Cylinder3D's sparse asymmetric U-Net on "
                            "distilkit.sparse, 7 point features, 32 channels — which loads the release's weights")
    frames: int = Field(1, ge=1, description="input scans fused (teacher: 4-5, student: 1)")
    channels: int = Field(32, ge=1, description="completion sub-network width (paper: 32)")
    point_mlp: list[Annotated[int, Field(ge=1)]] = Field(default_factory=lambda: [64, 128], min_length=1,
                                                         description="point MLP widths (paper: 64,128,256,256)")
    seg_channels: int = Field(32, ge=1, description="segmentation U-Net base width")
    kernels: list[Annotated[int, Field(ge=1, le=15)]] | None = Field(
        None, min_length=1, description="MPB path kernel sizes, odd, 1-15 (paper: 3,5,7 at 0.2 m; default: scaled to "
                                        "the grid so the receptive field stays ~1.6 m)")
    conv_kernel: int | None = Field(None, ge=1, le=15, description="ConvBlock kernel of the middle branch, odd, 1-15 "
                                                                   "(paper: 3; default: scaled to the grid)")
    semantics: Literal["spconv1", "spconv2"] = Field(
        "spconv1", description="size paper: spconv1 = SCPNet's release (spconv 1.2.1: a block's convolutions share "
                               "one indice_key and run on the first one's neighbourhood; its checkpoints), spconv2 = "
                               "Cylinder3D's spconv 2.x ports (a key per convolution, every kernel as written)")
    voxelization: Literal["release", "grid"] = Field(
        "release", description="size paper: release = SCPNet's dataloader (voxels of range / (grid - 1), 0.2008 m, "
                               "x shifted by -25.6 m in the point features), grid = the data's 0.2 m voxels and raw x")

    @field_validator("kernels", "conv_kernel")
    @classmethod
    def _odd(cls, v: Any) -> Any:
        sizes = v if isinstance(v, list) else [v] if v is not None else []
        if any(k % 2 == 0 for k in sizes):
            raise ValueError(f"kernel sizes must be odd (the grid stays aligned), got {v}")
        return v

    @model_validator(mode="after")
    def _one_size(self) -> "SCPNetParams":
        fields_of_one_size(self, {"tiny": ("channels", "point_mlp", "seg_channels", "kernels", "conv_kernel"),
                                  "paper": ("semantics", "voxelization")})
        return self


class SCPNetCard(MultiFrameLidarCard):
    """SCPNet's declarations (the adapter: :class:`distilkit_adapters.scpnet.adapter.SCPNetAdapter`)."""

    Params = SCPNetParams
    TAPS = {"completion": "sparse_features", "completion_dense": "volume_features", "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "ce", "weight": 1.0}, {"name": "lovasz", "weight": 1.0}]

    VERSION = 3  # 3: size paper in spconv 1.x semantics, the release's voxels; 2: grid-scaled kernels, empty
    # logits outside the active set, channels-last volumes
    NETWORKS = {"tiny": "CPU stand-in: the three-branch completion sub-network and a dense 2-scale U-Net",
                "paper": "the paper's network: the release's completion sub-network + Cylinder3D's sparse asymmetric "
                         "U-Net in spconv 1.x's key semantics (loads the release's spconv 1.x state dict; "
                         "semantics: spconv2 for Cylinder3D's spconv 2.x ports)"}

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        """The completion sub-network's dense volume lives on the data's grid, as its sparse tap does."""
        if tap == "completion_dense":
            return info.grid
        return super().tap_grid(tap, params, info)

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        out = super().check_data(params, info)
        grid = info.grid
        if getattr(params, "size") == "paper" and grid is not None and (
                grid.shape[0] % 16 or grid.shape[1] % 16 or grid.shape[2] % 4):
            out.append(("size", f"the paper's U-Net pools x and y four times and z twice: the grid {grid.shape} must "
                                "be divisible by 16 x 16 x 4 (SemanticKITTI's 256 x 256 x 32 at scale 1, 2 or 4)"))
        return out

    @classmethod
    def network(cls, params: BaseModel) -> str:
        if getattr(params, "size") == "paper" and getattr(params, "semantics") == "spconv2":
            return ("the paper's network with Cylinder3D's spconv 2.x ports' keys (a key per convolution, every "
                    "kernel as written: their checkpoints, not SCPNet's)")
        return super().network(params)

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """The paper's network (``size: paper``) runs sparse convolutions (distilkit.sparse); the stand-in none."""
        return getattr(params, "size") == "paper"

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return super().describe(params) + (", paper size" if getattr(params, "size") == "paper" else "")


ADAPTERS.declare("scpnet", "distilkit_adapters.scpnet.adapter:SCPNetAdapter", card=SCPNetCard,
                 description="SCPNet: multi-path-block completion sub-network + segmentation (dense U-Net stand-in)",
                 paper="Xia et al., SCPNet, CVPR 2023", consumes=tuple(SCPNetCard.TAPS.values()))
