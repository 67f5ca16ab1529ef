"""How distilkit sees JS3C-Net: taps ``logits``, ``point_logits`` (+ their ``point_target``), ``completion``
(sparse), ``ssc_dense``."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

import torch

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.data.lidar import select_frames
from distilkit.structures import VoxelGrid
from distilkit.registry import ADAPTERS
from distilkit.structures import SparseVoxels
from distilkit_adapters._blocks import MultiFrameLidarAdapter, channels_last, fields_of_one_size
from distilkit_adapters.js3cnet.model import JS3CNet


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


class JS3CNetAdapter(MultiFrameLidarAdapter):
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

    Params = JS3CNetParams
    TAPS = {"completion": "sparse_features", "ssc_dense": "volume_features", "logits": "voxel_logits",
            "point_logits": "point_logits", "point_target": "point_labels"}
    PREDICTION_TAP = "logits"
    DEFAULT_TASK_LOSSES = [{"name": "uncertainty_multitask", "weight": 1.0}]
    VERSION = 3  # 3: size paper as released (SparseConvNet); 2: channels-last volumes
    NETWORKS = {"tiny": "CPU stand-in: a dense U-Net on the completion grid, a 3-block SSC decoder, a residual PVI",
                "paper": "the paper's network as released: SparseConvNet's 7-level residual U-Net at 0.05 m, "
                         "SSCNet's decoder, the point-voxel interaction (loads the release's checkpoint)"}

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

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        if tap == "completion" and info.grid is not None:  # the SSC decoder works at half resolution
            return info.grid.coarsen(2)
        return super().tap_grid(tap, params, info)

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        return super().describe(params) + (", paper size" if getattr(params, "size") == "paper" else "")

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


ADAPTERS.add("js3cnet", JS3CNetAdapter,
             description="JS3C-Net: segmentation branch, SSC decoder and point-voxel interaction (size: tiny, a dense CPU "
                         "stand-in; size: paper, the release's sparse U-Net)",
             paper="Yan et al., JS3C-Net, AAAI 2021", consumes=tuple(JS3CNetAdapter.TAPS.values()))
