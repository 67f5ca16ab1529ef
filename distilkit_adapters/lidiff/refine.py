"""LiDiff's refinement stage (seed_code.md §3.3) as its own adapter, ``lidiff-refine``: a point network that predicts
six offsets per point of a diffusion completion (Linear(C -> 20), LeakyReLU, Linear(20 -> 18), tanh: each offset
in [-1, 1] m), so the refined scene holds 6x the points, trained with the Chamfer distance against the ground truth.

What it trains on (``train_on``): LiDiff trains its refinement on the aggregated ground truth jittered by Gaussian
noise (sigma 0.2 m, clipped at 0.3 m; ``SemanticKITTITemporalAggr.py``), not on a diffusion model's output, so the
refiner learns to densify and denoise any completion rather than one teacher's errors — the default,
``jittered-ground-truth``, from the batch's tiled ground-truth scene ``scene``. ``completions`` trains on the
completions of a frozen LiDiff model given as an auxiliary model (``aux: {diffusion: {from: teacher, inputs:
{completion: coarse}}}``; distilkit's earlier behaviour). Either way, evaluation refines the auxiliary model's
completion ``coarse``: with ground-truth training, the auxiliary model need not run on training batches
(``training: false`` on the aux edge), and an evaluation stage with another auxiliary model (the teacher at other
steps, a distilled student) scores that model refined. LiDiff's MinkUNet is replaced by per-point MLPs with a
k-nearest-neighbour edge descriptor of the completion itself, computed in chunks so that a 180,000-point completion
fits in memory.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from distilkit.adapter import Adapter
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.geometry.nearest import knn_indices
from distilkit.structures import PointCloud
from distilkit_adapters.lidiff.card import LiDiffRefineCard, RefineParams
from distilkit_adapters.lidiff.model import _mlp


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


class PaperRefiner(nn.Module):
    """LiDiff's refinement MinkUNet (``model_refine``): (M, 3) points -> (M, offsets, 3) tanh offsets."""

    def __init__(self, p: RefineParams) -> None:
        super().__init__()
        from distilkit_adapters.lidiff.minkunet import MinkUNet

        self.p = p
        self.model_refine = MinkUNet(out_channels=3 * p.offsets)

    def forward(self, points: Tensor) -> Tensor:
        return self.model_refine(points[None])[0].view(len(points), self.p.offsets, 3) * self.p.max_offset


class LiDiffRefineAdapter(LiDiffRefineCard, Adapter):
    """LiDiff's refinement network: ``coarse`` points in, ``refined`` (training) / ``completion`` (evaluation) out,
    ``offsets`` x as many points; the ``refine_cloud`` capability refines a completion for ``distilkit complete``."""

    CHOICES = (
        Choice("refinement training input", "the ground-truth scene jittered (sigma 0.2 m, clipped at 0.3 m)",
               "§3.4: trained to refine noisy completions", "jittered aggregated ground truth "
               "(SemanticKITTITemporalAggr.py)", "`train_on: completions` (a frozen LiDiff model's output)"),
    )

    def __init__(self, params: RefineParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net: nn.Module = PaperRefiner(params) if params.size == "paper" else PointRefiner(params)

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """A distilkit checkpoint, or LiDiff's released ``refine_net.ckpt`` (``model_refine.*``) converted to the
        paper-size network's names and layout."""
        from distilkit_adapters.lidiff.weights import from_lightning

        return from_lightning(super().read_weights(path), ("model_refine.",))

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

    def jittered(self, batch: Batch) -> PointCloud:
        """The batch's ground-truth scenes, each point moved by N(0, sigma^2) per axis clipped to +-clip (LiDiff's
        ``jitter_point_cloud(sigma=0.2, clip=0.3)``)."""
        scene = PointCloud(batch.field("scene"), batch.field("scene_lengths"))
        noise = (torch.randn_like(scene.points) * self.params.jitter_sigma).clamp(-self.params.jitter_clip,
                                                                                   self.params.jitter_clip)
        return PointCloud(scene.points + noise, scene.lengths)

    def forward(self, batch: Batch) -> dict[str, Any]:
        if self.training and self.params.train_on == "jittered-ground-truth":
            return {"refined": self.refine(self.jittered(batch))}
        coarse = batch.inputs.get("coarse")
        if coarse is None:
            raise ValueError("lidiff-refine refines the batch input 'coarse' (a frozen LiDiff model's completion: give "
                             "the stage `aux: {NAME: {from: STAGE, inputs: {completion: coarse}}}`)")
        if not isinstance(coarse, PointCloud):
            raise TypeError(f"lidiff-refine's input 'coarse' must be a point cloud (an auxiliary LiDiff model's "
                            f"completion), got {type(coarse).__name__}")
        refined = self.refine(coarse)
        return {"refined" if self.training else "completion": refined}


__all__ = ["LiDiffRefineAdapter", "PaperRefiner", "PointRefiner", "RefineParams"]
