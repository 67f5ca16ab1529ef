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

from typing import Any

import torch
from torch import Tensor

from distilkit.adapter import Adapter
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo
from distilkit_adapters._blocks import DenseUNet3d, channels_last
from distilkit_adapters.dean.card import DeanLabelerCard, DeanParams
from distilkit_adapters.dean.cylinder import WIDTHS, dense_inputs

EMPTY_LOGIT = 10.0  # class 0's logit outside the geometry; inside it, -EMPTY_LOGIT (a class is always chosen)


def geometry_logits(logits: Tensor, occupied: Tensor) -> Tensor:
    """Class scores that keep the geometry: outside ``occupied`` (B, X, Y, Z) the constant "empty" vector, inside it
    the network's scores with class 0 held far below (no gradient through either constant)."""
    inside = logits.clone()
    inside[:, 0] = -EMPTY_LOGIT
    empty = torch.zeros(logits.shape[1], dtype=logits.dtype, device=logits.device)
    empty[0] = EMPTY_LOGIT
    return torch.where(occupied.unsqueeze(1), inside, empty.view(1, -1, 1, 1, 1))


class DeanLabelerAdapter(DeanLabelerCard, Adapter):
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

    def __init__(self, params: DeanParams, info: DataInfo) -> None:
        super().__init__(params, info)
        if params.size == "paper":
            from distilkit_adapters.dean.cylinder import DeanCylinder

            self.net: Any = DeanCylinder(info.num_classes, params.features, params.semantics)
            return
        self.net = DenseUNet3d(WIDTHS[params.features], params.channels, params.channels)
        self.head = torch.nn.Conv3d(params.channels, info.num_classes, 1)
        channels_last(self)

    def forward(self, batch: Batch) -> dict[str, Any]:
        target = batch.field(self.params.geometry)
        occupied = (target != 0) & (target != self.info.classes.ignore_index)
        if self.params.size == "paper":
            features, logits = self.net(occupied)
            return {"features": features, "logits": geometry_logits(logits, occupied)}
        x = dense_inputs(occupied, self.params.features).contiguous(memory_format=torch.channels_last_3d)
        features = self.net(x)
        return {"features": features, "logits": geometry_logits(self.head(features), occupied)}


__all__ = ["DeanLabelerAdapter", "DeanParams", "geometry_logits"]
