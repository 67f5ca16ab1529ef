"""LiDiff's refinement stage (seed_code.md §3.3) as its own adapter, ``lidiff-refine``: a point network that predicts
six offsets per point of a diffusion completion (Linear(C -> 20), LeakyReLU, Linear(20 -> 18), tanh: each offset
in [-1, 1] m), so the refined scene holds 6x the points, trained with the Chamfer distance against the ground truth.

Its input ``coarse`` is the completion of a frozen LiDiff model given as an auxiliary model of the stage
(``aux: {diffusion: {from: teacher, inputs: {completion: coarse}}}``): the refiner trains on the diffusion model's
own completions, and an evaluation stage with another auxiliary model (the teacher at other steps, a distilled
student) scores that model refined. LiDiff's MinkUNet is replaced by per-point MLPs with a k-nearest-neighbour
edge descriptor of the completion itself, computed in chunks so that a 180,000-point completion fits in memory.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from distilkit.adapter import Adapter
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.geometry.nearest import knn_indices
from distilkit.registry import ADAPTERS
from distilkit.structures import PointCloud
from distilkit_adapters.lidiff.model import _gather, _mlp


class RefineParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    channels: int = Field(32, ge=4, description="width of the point MLPs")
    k: int = Field(8, ge=1, description="neighbours of each point's edge descriptor")
    offsets: int = Field(6, ge=1, description="points predicted per input point (LiDiff: 6)")
    max_offset: float = Field(1.0, gt=0, description="offsets lie in [-max_offset, max_offset] per axis (LiDiff: "
                                                     "tanh, 1 m)")
    chunk: int = Field(32768, ge=1, description="points per chunk of the descriptor (bounds memory, not results)")


class PointRefiner(nn.Module):
    """(M, 3) points -> (M, offsets, 3) offsets."""

    def __init__(self, p: RefineParams) -> None:
        super().__init__()
        self.p = p
        self.point = _mlp(3, p.channels, p.channels)
        self.edge = _mlp(p.channels + 3, p.channels, p.channels)
        self.body = _mlp(2 * p.channels, p.channels, p.channels)
        self.head = nn.Sequential(nn.Linear(p.channels, 20), nn.LeakyReLU(0.1), nn.Linear(20, 3 * p.offsets), nn.Tanh())

    def forward(self, points: Tensor) -> Tensor:
        centre = points.mean(dim=0, keepdim=True).detach()
        x = points - centre  # translation-free inputs; the offsets are relative anyway
        idx = knn_indices(x, x, self.p.k + 1)  # itself and its k nearest
        feats = self.point(x)
        out = []
        for s in range(0, len(x), self.p.chunk):
            i = idx[s:s + self.p.chunk]
            rel = x[i] - x[s:s + self.p.chunk, None]
            local = self.edge(torch.cat([feats[i], rel], dim=-1)).amax(dim=1)
            out.append(self.head(self.body(torch.cat([feats[s:s + self.p.chunk], local], dim=-1))))
        return torch.cat(out).view(len(x), self.p.offsets, 3) * self.p.max_offset


class LiDiffRefineAdapter(Adapter):
    """LiDiff's refinement network: ``coarse`` points in, ``refined`` (training) / ``completion`` (evaluation) out,
    ``offsets`` x as many points; the ``refine_cloud`` capability refines a completion for ``distilkit complete``."""

    Params = RefineParams
    INPUTS = frozenset({"coarse"})
    TAPS = {"refined": "points", "completion": "points"}
    PREDICTION_TAP = "completion"
    DEFAULT_TASK_LOSSES = [{"name": "chamfer", "taps": {"student": "refined"}}]
    VERSION = 1

    def __init__(self, params: RefineParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net = PointRefiner(params)

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return f"{getattr(params, 'offsets')}x refinement"

    def refine(self, coarse: PointCloud) -> PointCloud:
        """Each scene's points, each moved by its ``offsets`` predicted offsets: (B, offsets * M_b, 3)."""
        out = []
        for b in range(len(coarse.lengths)):
            pts = coarse.cloud(b)
            out.append((pts[:, None, :] + self.net(pts)).reshape(-1, 3))
        return PointCloud.from_list(out)

    def refine_cloud(self, points: np.ndarray) -> np.ndarray:
        """A completed scene (M, 3) refined to (offsets * M, 3), without gradient."""
        device = next(self.parameters()).device
        with torch.no_grad():
            pts = torch.from_numpy(np.ascontiguousarray(points, dtype=np.float32)).to(device)
            return (pts[:, None, :] + self.net(pts)).reshape(-1, 3).cpu().numpy()

    def forward(self, batch: Batch) -> dict[str, Any]:
        coarse = batch.inputs["coarse"]
        if not isinstance(coarse, PointCloud):
            raise TypeError(f"lidiff-refine's input 'coarse' must be a point cloud (an auxiliary LiDiff model's "
                            f"completion), got {type(coarse).__name__}")
        refined = self.refine(coarse)
        return {"refined" if self.training else "completion": refined}


ADAPTERS.add("lidiff-refine", LiDiffRefineAdapter,
             description="LiDiff's refinement: six offsets per point of a diffusion completion (Chamfer-trained), "
                         "on the completion of a frozen auxiliary LiDiff model",
             paper="Nunes et al., LiDiff, CVPR 2024 (models_refine.py)", consumes=tuple(LiDiffRefineAdapter.TAPS.values()))
