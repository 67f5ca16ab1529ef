"""The voxel-to-BEV distillation as an objective (Jiang et al., arXiv 2304.11393; release
fengjiang5/Knowledge-Distillation-from-Cylinder3D-to-PolarNet): a 3-D teacher's sparse voxels collapsed over height,
adapted on the teacher's side, against a bird's-eye student map. The maths is :mod:`distilkit.losses.bev`'s."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.objectives.bev import BEVCard, BEVParams
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.errors import DistilkitError, TapError
from distilkit.losses.bev import bev_from_voxels, collapse_height, column_weights
from distilkit.objectives.base import MultiTapObjective

_NO_PAPER = "not available to us (the stored copy holds the abstract)"


def release_adapter(teacher_channels: int, student_channels: int) -> nn.Module:
    """The release's teacher-side adapter (``Trans_dim``, ``kd/cross_attn_spconv121.py`` L9-20): BatchNorm, a 3x3
    convolution (zero padding), ReLU, BatchNorm."""
    return nn.Sequential(nn.BatchNorm2d(teacher_channels), nn.Conv2d(teacher_channels, student_channels, 3, padding=1),
                         nn.ReLU(inplace=True), nn.BatchNorm2d(student_channels))


class VoxelToBEV(BEVCard, MultiTapObjective):
    """Voxel-to-BEV distillation: the teacher's sparse voxels max-pooled over each column (empty columns 0), through
    the release's adapter (trained with the student), against the student's bird's-eye map by the label-weighted
    distance sqrt(mean_cells W sum_c (T - S)^2), W the column's sum of its voxels' class weights 1 / (f_c + 0.001)
    / 50 (f_c: the class's share of the training split's points, as the release; an empty or ignored voxel weighs
    as class 0, whose share is the unlabelled points');
    weight 2 (the release's). ``weighting: none``: the plain MSE of its voxel-to-pillar terms."""

    CHOICES = (Choice("the label-weighted term's layer", "the recipe's map pair (the plane of the labels or a "
                      "coarser one: the weights averaged over its blocks)", "the layer before classification "
                      "(Fig. 1)", "the level-0 encoder pair at 240 x 180 against a 480 x 360 weight map: the "
                      "released script fails at its first step (weight_mse.py L16)", ""),
               Choice("class weights", "1 / (f_c + 0.001) / 50, f_c this split's point shares (voxel shares where "
                      "it has no points)", _NO_PAPER, "the same formula on SemanticKITTI's point shares "
                      "(semantic-kitti.yaml's content); empty voxels count as class 0, the unlabelled points", ""),
               Choice("the target's gradient", "the adapter trains with the student (the teacher is frozen)",
                      "the knowledge-distillation model is updated (Fig. 1)", "the same: nothing is detached", ""),
               Choice("ties of the column max", "share the gradient (scatter_reduce)", _NO_PAPER,
                      "one voxel takes it (torch_scatter.scatter_max)", ""))

    def __init__(self, params: BEVParams) -> None:
        super().__init__(params)
        self.adapter: nn.Module = nn.Identity()
        self.register_buffer("class_weight", torch.ones(1))

    def prepare(self, train_set: Any) -> None:
        """The class weights 1 / (f_c + 0.001) / 50 of the training split: f_c the class's share of its points (the
        release's, from SemanticKITTI's point counts: class 0 the unlabelled points), or of its labelled voxels
        where the data has no points."""
        from distilkit.data.stats import label_counts

        voxels, points = label_counts(train_set, self.num_classes)
        counts = points if float(points.sum()) > 0 else voxels
        share = counts.double() / max(float(counts.sum()), 1.0)
        self.class_weight = (1.0 / (share + 0.001) / 50).to(self.class_weight)

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        s, t = taps["student"], taps["teacher"]
        cs, ct = s.shape[1], t.feats.shape[1]
        if self.params.adapter == "release":
            self.adapter = release_adapter(ct, cs)
        elif cs != ct:
            raise TapError(f"bev_from_voxels: the student's map has {cs} channels, the teacher's voxels {ct}: "
                           "keep `adapter: release`")

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        s, voxels = taps["student"], taps["teacher"]
        if s.dim() != 4:
            raise TapError(f"bev_from_voxels: the student's map must be (B, C, X, Y), got {tuple(s.shape)}")
        plane = collapse_height(voxels.detach(), self.params.collapse, batch=s.shape[0])
        if plane.shape[2:] != s.shape[2:]:
            raise TapError(f"bev_from_voxels: the teacher's plane {tuple(plane.shape[2:])} and the student's map "
                           f"{tuple(s.shape[2:])} differ (pair taps on one (X, Y) plane)")
        target = self.adapter(plane.to(s.dtype))
        weights = None
        if self.params.weighting == "labels":
            if self.class_weight.numel() != self.num_classes:
                raise DistilkitError("bev_from_voxels: the class weights were not prepared from the training split")
            weights = column_weights(taps["target"], self.class_weight.to(s.dtype), tuple(s.shape[2:]),
                                     self.ignore_index)
        return bev_from_voxels(s, target, weights, self.params.root)


__all__ = ["VoxelToBEV", "release_adapter"]
