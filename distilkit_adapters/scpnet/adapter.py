"""How distilkit sees SCPNet: taps ``completion`` (sparse), ``completion_dense``, ``logits``."""

from __future__ import annotations

from typing import Any

import torch

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit.data.lidar import select_frames
from distilkit.geometry.voxel import dense_to_sparse
from distilkit_adapters._blocks import MultiFrameLidarAdapter, channels_last
from distilkit_adapters.scpnet.card import SCPNetCard, SCPNetParams
from distilkit_adapters.scpnet.model import SCPNet, kernels_for_voxel, mask_inactive


class SCPNetAdapter(SCPNetCard, MultiFrameLidarAdapter):
    """SCPNet: MPB completion sub-network then segmentation; CE + Lovász task loss (eq. 4, alpha = 1). Its choices
    where the paper and the release differ (``CHOICES``): DSKD on the completion output, rectification from the
    current scan."""

    CHOICES = (
        Choice("DSKD's layer", "the completion sub-network's output (the `completion` tap) in every recipe",
               "§3.3 distils 'dense-to-sparse' completion features without pinning the layer",
               "DSKD is not in the release", "`taps: {student: TAP, teacher: TAP}`"),
        Choice("label rectification's scan", "the current scan's instance boxes (`rectify: true`)",
               "Algorithm 1, per frame", "rectifies with the 5 fused scans (multiscan = 4)"),
        Choice("sparse convolutions' shared keys (size: paper)", "spconv 1.x's reuse, as SCPNet's checkpoints were "
               "trained: a block's four convolutions on its first one's 1x3x3 or 3x1x3 offsets, an UpBlock's conv3 "
               "with its kernel's slice [:, 0], the ReconBlock's gates on 3x1x1 offsets",
               "§3.1 / Cylinder3D: asymmetric 1x3x3 / 3x1x3 / 3x3x3 kernels as written",
               "Codes-for-SCPNet (spconv 1.2.1): one indice_key per block; Cylinder3D's spconv 2.x ports: a key per "
               "convolution (bef1..bef4, up1..up3), every kernel as written", "`semantics: spconv2`"),
        Choice("voxelisation (size: paper)", "the release's: voxels of range / (grid - 1) (0.2008, 0.2008, 0.2065 m), "
               "x shifted by -25.6 m in the point features", "0.2 m voxels (SemanticKITTI's grid)",
               "dataset_semantickitti.py: intervals = crop_range / (grid_size - 1), xyz[:, 0] -= 25.6",
               "`voxelization: grid`"),
    )

    def __init__(self, params: SCPNetParams, info: DataInfo) -> None:
        super().__init__(params, info)
        if params.size == "paper":
            from distilkit_adapters.scpnet.cylinder import SCPNetPaper

            self.net: Any = SCPNetPaper(info.num_classes, semantics=params.semantics,
                                        voxelization=params.voxelization)
            return
        kernels, conv = kernels_for_voxel(info.grid.voxel_size)
        self.net = SCPNet(params.channels, params.point_mlp, params.seg_channels, info.num_classes,
                          tuple(params.kernels or kernels), params.conv_kernel or conv)
        channels_last(self)

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """A distilkit checkpoint, or the release's state dict (spconv 1.x weights) converted to the paper-size
        network's names and layout (:mod:`distilkit_adapters.scpnet.weights`)."""
        from distilkit_adapters.scpnet.weights import from_release

        return from_release(super().read_weights(path))

    def forward(self, batch: Batch) -> dict[str, Any]:
        b = select_frames(batch, self.params.frames)
        if self.params.size == "paper":
            sparse, completed, logits = self.net(b.inputs["points"], b.inputs["point_batch"], batch.size,
                                                 self.info.grid)
            return {"completion": sparse, "completion_dense": completed, "logits": logits}
        vox = self.net.voxelizer(b.inputs, self.info.grid, batch.size)
        completed = self.net.completion(vox)
        sparse = dense_to_sparse(completed, self.info.grid)
        active = torch.zeros(completed.shape[:1] + completed.shape[2:], dtype=torch.bool, device=completed.device)
        active[tuple(sparse.coords.T)] = True
        logits = mask_inactive(self.net.segmentation(completed), active)
        return {"completion": sparse, "completion_dense": completed, "logits": logits}



__all__ = ["SCPNetAdapter", "SCPNetParams"]
