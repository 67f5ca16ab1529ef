"""The VoxFormer-style camera models' cards (torch-free): their parameters (the ``size`` presets), taps and what
``validate`` asks of them; the networks are :mod:`distilkit_adapters.voxformer.adapter`'s."""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from distilkit.cards.base import AdapterCard
from distilkit.data.info import Camera, DataInfo
from distilkit.registry import ADAPTERS
from distilkit.structures import VoxelGrid
from distilkit_adapters._cards import CAMERA_INPUTS

SIZES: dict[str, dict[str, Any]] = {
    "tiny": {"widths": [8, 16, 32], "channels": 16, "heads": 2, "points": 4, "cross_layers": 2, "mix_layers": 1,
             "bev_width": 16, "encoder": "small", "mixing": "conv"},
    "paper": {"widths": [64, 128, 256, 512, 1024], "channels": 128, "heads": 8, "points": 8, "cross_layers": 3,
              "mix_layers": 2, "bev_width": 64, "encoder": "resnet50", "mixing": "deformable-plane"},
}
Width = Annotated[int, Field(ge=1)]


class _SizedParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    size: Literal["tiny", "paper"] = Field("tiny", description="preset of the fields below left unset: tiny (CPU, "
                                                               "tests) or paper (VoxFormer's)")
    widths: list[Width] | None = Field(None, min_length=2, description="encoder stage widths; the output stride is "
                                                                       "2 ** (stages - 1) (paper: 16)")
    channels: int | None = Field(None, ge=1, description="FPN and query channels (paper: 128)")

    def value(self, name: str) -> Any:
        """A field's value, or the size preset's where the recipe left it unset."""
        given = getattr(self, name)
        return SIZES[self.size][name] if given is None else given


class ProposalParams(_SizedParams):
    bev_width: int | None = Field(None, ge=1, description="width of the bird's-eye U-Net (LMSCNet-style)")
    max_depth: float = Field(80.0, gt=0, description="largest depth the depth head predicts (metres)")


class VoxFormerParams(_SizedParams):
    heads: int | None = Field(None, ge=1, description="cross-attention heads (paper: 8)")
    points: int | None = Field(None, ge=1, description="sampling points per head and frame (paper: 8)")
    cross_layers: int | None = Field(None, ge=1, description="deformable cross-attention layers (paper: 3)")
    mix_layers: int | None = Field(None, ge=0, description="layers that mix the query volume (paper: 2 deformable "
                                                           "self-attention layers)")
    encoder: Literal["small", "resnet50"] | None = Field(
        None, description="small: the CPU stand-in (a ResNet of basic blocks, `widths`, and the fields below); "
                          "resnet50: VoxFormer's network as released (ResNet-50 to its third stage with torchvision's "
                          "names, frozen batch norms and first stage, FPN, its transformers; loads a released "
                          "checkpoint, and `init: {checkpoint: resnet50-19c8e357.pth}` ImageNet weights)")
    mixing: Literal["conv", "deformable-3d", "deformable-plane"] | None = Field(
        None, description="how the query volume is mixed: conv (residual 3-D convolutions, the small stand-in only), "
                          "deformable-plane (the released VoxFormer-S/T checkpoints: 2-D deformable self-attention "
                          "over the flat queries folded to a 512 x 512 plane) or deformable-3d (the paper's text and "
                          "the release's deform3D configs: trilinear in the volume)")
    frames: int = Field(1, ge=1, description="images read: the current one and the frames before it the data gives "
                                             "(VoxFormer-S: 1, VoxFormer-T: 5)")
    geometry: Literal["proposals", "ground-truth"] = Field(
        "proposals", description="where the occupied queries come from: the batch input `proposal` (a frozen "
                                 "stage-1 model's scores through an aux edge, or a folder of VoxFormer's proposal "
                                 "files: data.params.proposals) or the dense ground truth at half resolution "
                                 "(Scribble2Scene's Teacher-Labeler)")

    @model_validator(mode="after")
    def _encoder_widths(self) -> "VoxFormerParams":
        if self.value("encoder") == "resnet50" and self.widths is not None:
            raise ValueError("`widths` sizes the small encoder; encoder: resnet50 has ResNet-50's")
        if self.value("encoder") == "resnet50" and self.value("mixing") == "conv":
            raise ValueError("mixing: conv is the small stand-in's; encoder: resnet50 (VoxFormer as released) mixes "
                             "by deformable-plane or deformable-3d self-attention")
        return self


def _camera_problems(info: DataInfo, frames: int = 1) -> list[tuple[str, str]]:
    if not info.cameras:
        return [("", "the data has no camera (set data.params.camera, e.g. `camera: {}`, on synthetic-lidar or a "
                     "SemanticKITTI folder)")]
    if frames > len(info.cameras[0].frames):
        return [("frames", f"{frames} images requested, but the data gives {len(info.cameras[0].frames)} per sample "
                           "(data.params.camera.previous)")]
    return []


class VoxFormerProposalCard(AdapterCard):
    """VoxFormer's stage 1's declarations (the adapter:
    :class:`distilkit_adapters.voxformer.adapter.VoxFormerProposalAdapter`)."""

    Params = ProposalParams
    NETWORKS = {size: "CPU stand-in at both sizes: a depth head and a bird's-eye U-Net (VoxFormer's stage 1 is "
                      "MobileStereoNet + LMSCNet: read its proposal files with data.params.proposals instead)"
                for size in ("tiny", "paper")}
    INPUTS = CAMERA_INPUTS
    TAPS = {"depth": "depth_map", "occupancy": "occupancy_logits"}
    DATA_PARAMS = {"camera": {}}  # a camera on the data (synthetic-lidar renders one)
    PREDICTION_TAP = "occupancy"
    DEFAULT_TASK_LOSSES = [{"name": "occupancy_ce", "weight": 1.0},
                           {"name": "depth_l1", "weight": 0.1, "params": {"sky_depth": 80.0}}]

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        return info.grid.coarsen(2) if tap == "occupancy" and info.grid is not None else None

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        return _camera_problems(info)

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """No sparse convolutions at either size."""
        return False

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return "camera, query proposals"


class VoxFormerCard(AdapterCard):
    """VoxFormer's stage 2's declarations (the adapter:
    :class:`distilkit_adapters.voxformer.adapter.VoxFormerAdapter`)."""

    Params = VoxFormerParams
    NETWORKS = {"tiny": "CPU stand-in: a small ResNet of basic blocks, 3-D convolutions mixing the queries",
                "paper": "the paper's network as released: ResNet-50 + FPN, deformable cross- and self-attention "
                         "(loads a released VoxFormer checkpoint, or torchvision's ResNet-50 file)"}

    @classmethod
    def network(cls, params: BaseModel) -> str:
        encoder, mixing = params.value("encoder"), params.value("mixing")  # type: ignore[attr-defined]
        if encoder == "resnet50":
            return cls.NETWORKS["paper"] + f" ({mixing[len('deformable-'):]})"
        if mixing == "conv":
            return cls.NETWORKS["tiny"]
        return f"CPU stand-in: a small ResNet of basic blocks, {mixing} self-attention over the queries"

    TAPS = {"image_features": "image_features", "query_features": "sparse_features", "logits": "voxel_logits"}
    DATA_PARAMS = {"camera": {}}
    AUX_INPUTS = {"proposal": "voxformer-proposal"}  # stage 1's occupancy (``geometry: proposals``)
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "weighted_ce", "weight": 1.0}, {"name": "sem_scal", "weight": 1.0},
                           {"name": "geo_scal", "weight": 1.0}]

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        geometry = "proposal" if getattr(params, "geometry") == "proposals" else "voxel_target"
        return CAMERA_INPUTS | {geometry}

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        if info.grid is None:
            return None
        return {"query_features": info.grid.coarsen(2), "logits": info.grid}.get(tap)

    @classmethod
    def tap_camera(cls, tap: str, params: BaseModel, info: DataInfo) -> Camera | None:
        """The data's camera with the frames the model reads: image features of one frame and of five are not one
        camera's (``validate`` refuses to compare them)."""
        if tap != "image_features" or not info.cameras:
            return None
        return dataclasses.replace(info.cameras[0], frames=info.cameras[0].frames[:getattr(params, "frames")])

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        return _camera_problems(info, getattr(params, "frames"))

    @classmethod
    def sparse(cls, params: BaseModel) -> bool:
        """No sparse convolutions at either size."""
        return False

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        frames = int(getattr(params, "frames"))
        geometry = "ground-truth geometry" if getattr(params, "geometry") == "ground-truth" else "proposals"
        return f"camera, {frames} image{'s' if frames > 1 else ''}, {geometry}"


ADAPTERS.declare("voxformer-proposal", "distilkit_adapters.voxformer.adapter:VoxFormerProposalAdapter",
                 card=VoxFormerProposalCard,
                 description="VoxFormer stage 1: depth from the image, lifted, completed to half-resolution occupancy",
                 paper="Li et al., VoxFormer, CVPR 2023 (stage 1, query proposals)",
                 consumes=tuple(VoxFormerProposalCard.TAPS.values()))
ADAPTERS.declare("voxformer", "distilkit_adapters.voxformer.adapter:VoxFormerAdapter", card=VoxFormerCard,
                 description="VoxFormer stage 2: voxel queries with deformable cross-attention to the images, 3-D "
                             "mixing, x2 completion head (geometry: proposals, or ground-truth for the "
                             "Teacher-Labeler)",
                 paper="Li et al., VoxFormer, CVPR 2023; Wang et al., Scribble2Scene, IJCAI 2024 (Teacher-Labeler)",
                 consumes=tuple(VoxFormerCard.TAPS.values()))
