"""A worked example: a user's own SSC model plugged into distilkit as an adapter (docs/tutorials/your-own-model.md
§1-2, whose code blocks are this file; a test keeps them the same).

The model is deliberately small: points are max-pooled into voxels, a few 3-D convolutions
complete the volume, and a 1x1x1 convolution gives class logits. The adapter tells distilkit
which taps it returns, so any registered objective can distil into it -- here DSKD from an
SCPNet teacher (see ``recipe.yaml`` beside this file).
"""

from __future__ import annotations

from typing import Any

import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.data.lidar import LIDAR_INPUTS, frames_problems, select_frames
from distilkit.geometry.voxel import dense_to_sparse
from distilkit.registry import ADAPTERS


class TinyParams(BaseModel):                  # the adapter's parameters: a recipe's `model.params`
    model_config = ConfigDict(extra="forbid")  # unknown parameters are errors (`validate` names the valid ones)
    frames: int = Field(1, ge=1, description="input scans to use")
    channels: int = Field(8, ge=1, description="width of the convolutions")


class TinySSC(Adapter):
    """Voxel max-pooling, three bias-free 3x3x3 convolutions, a 1x1x1 classifier."""

    Params = TinyParams                        # pydantic model: your constructor parameters
    INPUTS = LIDAR_INPUTS                      # batch inputs forward reads: points, point_batch, point_frame
    TAPS = {"features": "sparse_features",     # tap name -> tap kind
            "logits": "voxel_logits"}
    PREDICTION_TAP = "logits"                  # what evaluation scores (by the metrics for its kind)
    DEFAULT_TASK_LOSSES = [{"name": "ce", "weight": 1.0}]

    def __init__(self, params: TinyParams, info: DataInfo) -> None:  # info: grid, class table, cameras, fields
        super().__init__(params, info)
        c = params.channels
        self.embed = nn.Linear(4, c)
        self.body = nn.Sequential(*[m for _ in range(3) for m in (nn.Conv3d(c, c, 3, padding=1, bias=False), nn.ReLU())])
        self.head = nn.Conv3d(c, info.num_classes, 1)

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        return frames_problems(params, info)  # optional: `validate` rejects more frames than the data has

    def forward(self, batch: Batch) -> dict[str, Any]:
        inputs = select_frames(batch, self.params.frames).inputs  # the current scan and the next frames - 1
        grid = self.info.grid                  # the data's voxel grid: origin, voxel size, shape
        idx, inside = grid.index(inputs["points"][:, :3])  # each point's voxel (M, 3), and whether it is inside
        x, y, z = grid.shape
        flat = ((inputs["point_batch"] * x + idx[:, 0]) * y + idx[:, 1]) * z + idx[:, 2]
        feats = torch.relu(self.embed(inputs["points"][inside]))
        vol = feats.new_zeros(batch.size * x * y * z, feats.shape[1])  # max-pool the points into their voxels
        vol = vol.scatter_reduce(0, flat[inside, None].expand_as(feats), feats, "amax", include_self=False)
        dense = vol.view(batch.size, x, y, z, -1).permute(0, 4, 1, 2, 3)
        completed = self.body(dense)
        # sparse features carry their grid, so objectives can align them with another model's voxels
        return {"features": dense_to_sparse(completed, grid), "logits": self.head(completed)}


def register() -> None:
    """The entry point: ``[project.entry-points."distilkit.plugins"] tiny = "tiny_adapter:register"``."""
    ADAPTERS.add("tiny-ssc", TinySSC, description="a tiny user model (worked example)",
                 paper="docs/tutorials/your-own-model.md", consumes=tuple(TinySSC.TAPS.values()))
