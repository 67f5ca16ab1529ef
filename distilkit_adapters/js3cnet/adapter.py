"""How distilkit sees JS3C-Net: taps ``logits``, ``point_logits`` (+ their ``point_target``), ``completion``
(sparse), ``ssc_dense``."""

from __future__ import annotations

from typing import Any

import torch

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.data.lidar import select_frames
from distilkit.structures import SparseVoxels
from distilkit_adapters._blocks import MultiFrameLidarAdapter, channels_last
from distilkit_adapters.js3cnet.card import JS3CNetCard, JS3CNetParams
from distilkit_adapters.js3cnet.model import JS3CNet


class JS3CNetAdapter(JS3CNetCard, MultiFrameLidarAdapter):
    """JS3C-Net with the uncertainty-weighted multi-task loss (eq. 2) as its task loss. Its choices against the paper
    and the release (``CHOICES``): 3 SSC decoder blocks, segmentation on the 0.2 m grid, a residual refinement."""

    CHOICES = (
        Choice("SSC decoder blocks", "3 residual blocks (the last two dilated by 2)",
               "supplement: five basic blocks of 32 channels", "SSCNet_Decoder: 5 blocks", "`ssc_channels` sets the width only"),
        Choice("segmentation resolution", "size tiny: a dense U-Net on the 0.2 m completion grid (CPU-sized); size "
               "paper: 0.05 m (`seg_voxel`)", "§4: 0.05 m grids for the SparseConv U-Net",
               "args.txt of the released checkpoint: scale 20 (0.05 m); JS3C_default_kitti.yaml: scale 10", ""),
        Choice("PVI queries (size: paper)", "every non-zero coarse voxel queries its k nearest supports and is fused, "
               "the others stay 0 (`pvi_queries: all`)", "§3.3: the coarse completion's voxels",
               "the same (262,144 queries at 256 x 256 x 32; nanoflann's k-d tree)",
               "`pvi_queries: near`: only voxels occupied or next to one query, every voxel fused (faster)"),
        Choice("PVI neighbour ties (size: paper)", "exact k nearest, equidistant supports (voxel centres on a grid) "
               "taken by the lower voxel index", "not said", "nanoflann: its tree's order", ""),
        Choice("voxel pooling (size: paper)", "mean over 5 slots of each voxel's first `fuse_k` points in scan order, a "
               "voxel with fewer padded with its first point", "§3.2: mean pooling",
               "the same at batch 1; with several scans Merge's offset makes the padding the batch's first point", ""),
        Choice("completion voxel z (size: paper)", "each point's voxel raised by 1 (`z_offset: 1`), one raised past "
               "the grid dropped", "not said", "train.py / test_kitti_ssc.py: coords[:, 3] += 1 ('SemanticKITTI will "
               "generate [256,256,31]')", "`z_offset: 0`"),
        Choice("segmentation input (size: paper)", "the scan as it is, its voxels aligned to the six poolings",
               "not said", "kitti_dataset.process_seg_data rotates, scales and shifts the scan at random at every "
               "call, test time included", ""),
        Choice("point classifier (size: paper)", "`linear` m -> K - 1 (the release's 19); the `point_logits` tap puts "
               "class 0 (unlabelled, never a target) first, 10^4 below a point's lowest logit (no gradient), so its "
               "softmax is the 19 classes' (exp(-10^4) is 0)", "19 classes", "`linear` 16 -> 19", ""),
        Choice("PVI refinement", "size tiny: residual, FC([aggregated, coarse logits]) added to the coarse logits",
               "Fig. 3: the PVI output replaces the coarse completion", "FC(m + 20 -> 20) replaces them (size paper, "
               "as released)"),
        Choice("logits (size: paper)", "`upsample` ends with a ReLU, as released: the logits are >= 0", "not said",
               "SSCNet.py: Conv3d, BatchNorm3d, ReLU, PixelShuffle3D", ""),
    )

    def __init__(self, params: JS3CNetParams, info: DataInfo) -> None:
        super().__init__(params, info)
        if params.size == "paper":
            from distilkit_adapters.js3cnet.paper import JS3CNetPaper

            self.net: Any = JS3CNetPaper(info.num_classes, params.seg_channels, params.levels, params.ssc_channels,
                                         params.knn, params.fuse_k, params.pvi_queries, params.seg_voxel,
                                         params.z_offset)
            return
        self.net = JS3CNet(info.grid, info.num_classes, params.seg_channels, params.embed, params.ssc_channels,
                           params.pvi_hidden, params.knn)
        channels_last(self)

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """A distilkit checkpoint, or the release's ``model_*.pth`` under the paper-size network's names
        (:mod:`distilkit_adapters.js3cnet.weights`)."""
        from distilkit_adapters.js3cnet.weights import from_release

        return from_release(super().read_weights(path))

    def forward(self, batch: Batch) -> dict[str, Any]:
        b = select_frames(batch, self.params.frames)
        if self.params.size == "paper":
            out = self.net(b.inputs["points"], b.inputs["point_batch"], batch.size, self.info.grid)
            out["point_keep"] = torch.ones(len(b.inputs["points"]), dtype=torch.bool, device=out["logits"].device)
            labelled = out["point_logits"]  # K - 1 labelled classes; class 0 (never a target) 10^4 below them
            floor = labelled.detach().amin(1, keepdim=True) - 1e4 if len(labelled) else labelled[:, :1]
            out["point_logits"] = torch.cat([floor, labelled], 1)
        else:
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


__all__ = ["JS3CNetAdapter", "JS3CNetParams"]
