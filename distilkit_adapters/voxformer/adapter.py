"""How distilkit sees the VoxFormer-style camera models: ``voxformer-proposal`` (stage 1, query proposals from
predicted depth) and ``voxformer`` (stage 2; with ``geometry: ground-truth`` Scribble2Scene's Teacher-Labeler).

Stage 2 reads its proposals from a frozen stage-1 model through an auxiliary edge (``aux: {proposal: {from: ...}}``
puts the proposal model's occupancy scores in the batch as ``proposal``), not as a teacher, or from a folder of
VoxFormer's proposal files (``data.params.proposals``). Its size is a parameter: ``size: tiny`` (the CPU stand-in: a
small ResNet of basic blocks, 3-D convolutions mixing the queries) for tests and CPUs, ``size: paper`` for
VoxFormer's network as released (:mod:`.release`: ResNet-50 to its stride-16 stage + FPN, 128 channels, 3 deformable
cross-attention and 2 deformable self-attention layers, 8 heads and points, which loads a released checkpoint); any
single field given overrides the preset.
"""

from __future__ import annotations

from typing import Any

from distilkit.adapter import Adapter
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.geometry.voxel import pool_occupancy
from distilkit_adapters.voxformer.card import (SIZES, ProposalParams, VoxFormerCard, VoxFormerParams,
                                               VoxFormerProposalCard)
from distilkit_adapters.voxformer.model import VoxFormerNet
from distilkit_adapters.voxformer.proposal import QueryProposal
from distilkit_adapters.voxformer.release import VoxFormerRelease
from distilkit_adapters.voxformer.weights import from_mmdet, from_torchvision

class VoxFormerProposalAdapter(VoxFormerProposalCard, Adapter):
    """VoxFormer's stage 1: depth from the current image, lifted and completed to half-resolution occupancy. Its
    choice (``CHOICES``): monocular depth from one frame where VoxFormer lifts stereo depth of 10 sweeps."""

    CHOICES = (
        Choice("stage-1 depth", "a monocular depth head trained with the data's depth, the current image only",
               "§3.2: depth from a stereo network (MobileStereoNet), lifted to a pseudo point cloud",
               "query proposals precomputed from MSNet3D depth of 10 sweeps (sequences_msnet3d_sweep10)"),
    )

    def __init__(self, params: ProposalParams, info: DataInfo) -> None:
        super().__init__(params, info)
        self.net = QueryProposal(params.value("widths"), params.value("channels"), params.value("bev_width"),
                                 info.grid.coarsen(2), params.max_depth)

    def forward(self, batch: Batch) -> dict[str, Any]:
        b = batch.inputs
        depth, occupancy = self.net(b["image"][:, 0], b["intrinsics"][:, 0], b["lidar_to_camera"][:, 0])
        return {"depth": depth, "occupancy": occupancy}


class VoxFormerAdapter(VoxFormerCard, Adapter):
    """VoxFormer's stage 2: proposed voxel queries read the images by deformable cross-attention; CE (VoxFormer's
    class weights, mean over valid voxels) + sem_scal + geo_scal (seed_code.md §5). Its choices (``CHOICES``):
    sampling offsets per image, ``align_corners`` of the samplings."""

    CHOICES = (
        Choice("deformable sampling offsets", "size paper: one set per head and point, shared by every image, as "
               "released; size tiny: predicted per image (head x image x point)", "not stated",
               "one set per head, level and point, shared by every image (BEVFormer's spatial cross-attention)"),
        Choice("align_corners", "size paper: as released (grid_sample False, the header's trilinear x2 True); size "
               "tiny: False everywhere", "not stated", "grid_sample with align_corners=False (mmcv's deformable "
               "attention); the Header's nn.Upsample(scale_factor=2, trilinear) with align_corners=True"),
        Choice("self-attention (size: paper)", "2-D over the queries folded to a 512 x 512 plane, 2 queues (value = "
               "the query twice, offsets from [query, query + position], the reads averaged), the released "
               "checkpoints' (`mixing: deformable-plane`)", "§3.3: deformable self-attention over the voxel queries "
               "(3-D)", "voxformer-S.py / -T.py: DeformSelfAttention (2-D); *_deform3D.py: the 3-D one, whose layer "
               "passes a 2-D spatial shape (taken here as the volume's)", "`mixing: deformable-3d`"),
        Choice("positional encoding (size: paper)", "learned row and column embeddings (512 x 64 each) of the 512 x 512 "
               "plane, in the self-attention only", "not stated", "LearnedPositionalEncoding; VoxFormerLayer passes "
               "no position to the cross-attention", ""),
        Choice("several samples in a batch (size: paper)", "each sample with its own proposals and queries",
               "not stated", "batch 1: the first sample's proposals; the self-attention's offsets take the first "
               "sample's queries (value[:bs])", ""),
    )

    def __init__(self, params: VoxFormerParams, info: DataInfo) -> None:
        super().__init__(params, info)
        v = params.value
        if v("encoder") == "resnet50":
            self.net: Any = VoxFormerRelease(info.grid, info.num_classes, v("channels"), v("heads"), v("points"),
                                             v("cross_layers"), v("mix_layers"), params.frames,
                                             v("mixing")[len("deformable-"):])
        else:
            self.net = VoxFormerNet(v("widths"), v("channels"), v("heads"), v("points"), params.frames,
                                    v("cross_layers"), v("mix_layers"), info.num_classes, info.grid, v("mixing"))

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """A distilkit checkpoint or state dict, a released VoxFormer checkpoint (mmdet's ``state_dict`` of
        ``img_backbone``, ``img_neck``, ``pts_bbox_head``), or torchvision's ResNet-50 ImageNet file
        (``resnet50-19c8e357.pth``) for the ``encoder: resnet50`` backbone alone (the rest of the model keeps its
        initial weights; use it as a stage's ``init``); :mod:`.weights`."""
        return from_mmdet(from_torchvision(super().read_weights(path)))

    def occupied(self, batch: Batch) -> Any:
        """(B, X/2, Y/2, Z/2) bool: the queries that read the images."""
        shape = self.net.query_grid.shape
        if self.params.geometry == "ground-truth":
            return pool_occupancy(batch.field("voxel_target").long(), 2, self.info.classes.ignore_index) == 1
        proposal = batch.field("proposal")
        dims = ", ".join(map(str, shape))
        if proposal.dim() == 4 and tuple(proposal.shape[1:]) == tuple(shape):  # occupancy read from a folder
            return proposal != 0
        if proposal.dim() != 5 or proposal.shape[1] != 2 or tuple(proposal.shape[2:]) != tuple(shape):
            raise ValueError(f"voxformer: the batch input `proposal` must be (B, 2, {dims}) empty/occupied scores "
                             f"(a voxformer-proposal stage through an aux edge) or (B, {dims}) occupancy "
                             f"(data.params.proposals), got {tuple(proposal.shape)}")
        return proposal.argmax(dim=1) == 1

    def forward(self, batch: Batch) -> dict[str, Any]:
        frames = self.params.frames
        b = batch.inputs
        feats, queries, logits = self.net(b["image"][:, :frames], b["intrinsics"][:, :frames],
                                          b["lidar_to_camera"][:, :frames], self.occupied(batch))
        return {"image_features": feats.flatten(1, 2), "query_features": queries, "logits": logits}


__all__ = ["SIZES", "ProposalParams", "VoxFormerAdapter", "VoxFormerParams", "VoxFormerProposalAdapter"]
