"""How distilkit sees Scribble2Scene's Dean-Labeler (Wang et al. IJCAI 2024, §4.2, eq. 1, §5.1).

The Dean-Labeler takes the complete geometry as input, so scene completion becomes voxel segmentation: a network
reads the occupied voxels of the geometry field (the ground truth's, no image) and labels each with a class; empty
voxels stay empty (the network does not change the geometry: IoU 100 %, Table 3). Trained with partial CE on the
scribbles (non-empty, labelled voxels only; batch 4 on one GPU in the paper); its predictions, published, become the
camera student's labels (``labels: {from: dean, keep: scribble}``).

* ``size: paper`` — the paper's network (§5.1: "we adopt Cylinder3D as the SCN backbone"): Cylinder3D's asymmetric
  sparse U-Net, the SCPNet adapter's, on the occupied voxels (:mod:`distilkit_adapters.dean.cylinder`).
* ``size: tiny`` — the CPU stand-in: the dense 3-D U-Net the LiDAR adapters share, on the same inputs.

Neither the paper nor a release pins the voxels' input features (the Dean-Labeler's code is not released: the
authors' repository, songw-zju/Scribble2Scene, holds Stage II only), see ``CHOICES``.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor

from distilkit.adapter import Adapter
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.registry import ADAPTERS
from distilkit_adapters._blocks import DenseUNet3d, channels_last, fields_of_one_size
from distilkit_adapters.dean.cylinder import WIDTHS, Features, dense_inputs

EMPTY_LOGIT = 10.0  # class 0's logit outside the geometry; inside it, -EMPTY_LOGIT (a class is always chosen)


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

    CHOICES = (
        Choice("the Dean-Labeler's input features", "`height`: at every occupied voxel a 1 and its height scaled to "
               "[-1, 1] (sparse convolutions see shape, not place: the height tells a road from a roof of the same "
               "local shape)", "§4.2: the complete geometry G is the input (its occupancy); the features are not "
               "stated", "not released (songw-zju/Scribble2Scene holds Stage II only); Cylinder3D itself reads "
               "point features (positions, cylinder coordinates, intensity) pooled per voxel",
               "`features: occupancy` (G alone) or `features: position` (x, y, z)"),
        Choice("the Dean-Labeler's sparse convolutions' shared keys (size: paper)", "spconv 1.x's reuse, as "
               "Cylinder3D's release runs them (a block's convolutions on its first one's offsets)",
               "§5.1: Cylinder3D (its asymmetric 1x3x3 / 3x1x3 / 3x3x3 kernels as written)",
               "Cylinder3D's release (spconv 1.2.1): one indice_key per block; its spconv 2.x ports: a key per "
               "convolution", "`semantics: spconv2`"),
        Choice("the Dean-Labeler's loss and schedule", "partial CE, the unweighted mean over the scribbled non-empty "
               "voxels; recipes/paper/scribble2scene.yaml: batch 4, Adam at lr 1e-3 for 40 epochs",
               "eq. 1: CE summed over the scribbled non-empty voxels; §5.1: batch 4 on one GPU, no optimizer or "
               "epochs stated", "not released; Cylinder3D's release (config/semantickitti.yaml, "
               "train_cylinder_asym.py): Adam, lr 1e-3, 40 epochs, batch 2, weighted CE + Lovász",
               "the stage's `task_losses`, `optimizer` and `train`"),
    )

    Params = DeanParams
    NETWORKS = {"tiny": "CPU stand-in: the dense U-Net the LiDAR adapters share (the paper's is Cylinder3D)",
                "paper": "the paper's network: Cylinder3D's asymmetric sparse U-Net (the SCPNet adapter's, without "
                         "its completion sub-network) on the complete geometry's occupied voxels"}
    TAPS = {"features": "volume_features", "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "partial_ce", "weight": 1.0, "params": {"class_weights": "none"}}]
    VERSION = 2  # 2: size paper (Cylinder3D), input features as a parameter (tiny's default unchanged)

    def __init__(self, params: DeanParams, info: DataInfo) -> None:
        super().__init__(params, info)
        if params.size == "paper":
            from distilkit_adapters.dean.cylinder import DeanCylinder

            self.net: Any = DeanCylinder(info.num_classes, params.features, params.semantics)
            return
        self.net = DenseUNet3d(WIDTHS[params.features], params.channels, params.channels)
        self.head = torch.nn.Conv3d(params.channels, info.num_classes, 1)
        channels_last(self)

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        return frozenset({getattr(params, "geometry")})

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        grid = info.grid
        if getattr(params, "size") == "paper" and grid is not None and (
                grid.shape[0] % 16 or grid.shape[1] % 16 or grid.shape[2] % 4):
            return [("size", f"Cylinder3D's U-Net pools x and y four times and z twice: the grid {grid.shape} must "
                             "be divisible by 16 x 16 x 4 (SemanticKITTI's 256 x 256 x 32 at scale 1, 2 or 4)")]
        return []

    def forward(self, batch: Batch) -> dict[str, Any]:
        target = batch.field(self.params.geometry)
        occupied = (target != 0) & (target != self.info.classes.ignore_index)
        if self.params.size == "paper":
            features, logits = self.net(occupied)
            return {"features": features, "logits": geometry_logits(logits, occupied)}
        x = dense_inputs(occupied, self.params.features).contiguous(memory_format=torch.channels_last_3d)
        features = self.net(x)
        return {"features": features, "logits": geometry_logits(self.head(features), occupied)}

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return "complete geometry" + (", paper size" if getattr(params, "size") == "paper" else "")


ADAPTERS.add("dean-labeler", DeanLabelerAdapter,
             description="Scribble2Scene's Dean-Labeler: voxel segmentation of the complete geometry (partial CE on "
                         "scribbles; size paper: Cylinder3D); its published predictions are pseudo-labels",
             paper="Wang et al., Scribble2Scene, IJCAI 2024 (§4.2, eq. 1; §5.1: Cylinder3D, batch 4)",
             consumes=tuple(DeanLabelerAdapter.TAPS.values()))
