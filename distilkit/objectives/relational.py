"""Relational objectives on sparse voxel features: PKT over sampled voxels and PVKD."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from distilkit.cards.objectives.relational import PKTCard, PKTParams, PVKDCard, PVKDParams
from distilkit.data.batch import Batch
from distilkit.losses.feature import pkt
from distilkit.losses.pvkd import pvkd, supervoxel_ids, supervoxel_radial_bin
from distilkit.objectives.base import MultiTapObjective, Objective
from distilkit.objectives.common import aligned_pairs, voxel_mask
from distilkit.structures import SparseVoxels


class PKT(PKTCard, Objective):
    """PKT (Passalis & Tefas, ECCV 2018) over voxels sampled from each scene's active set.

    Batches in SSC hold 1-4 scenes, so the probability distributions are built across voxels, not
    across samples. Default weight 500 = RepDistiller's 30000 at B = 64 rescaled by ``per_row``.
    Alignment as DSKD: the student's voxels are the reference; across grids a coarser teacher is
    read at the parent voxel, a finer one mean-pooled into the student's voxels.
    """

    def forward(self, student: SparseVoxels, teacher: SparseVoxels, batch: Batch) -> Tensor:
        fs, ft, found = aligned_pairs(student, teacher)
        b = student.coords[:, 0]
        losses = []
        for i in torch.unique(b).tolist():
            rows = ((b == i) & found) if self.params.shared_only and bool(((b == i) & found).any()) else (b == i)
            idx = rows.nonzero().squeeze(1)
            if idx.numel() > self.params.sample_size:
                idx = idx[torch.randperm(idx.numel(), device=idx.device)[: self.params.sample_size]]
            value = pkt(fs[idx], ft[idx])
            losses.append(value * idx.numel() if self.params.per_row else value)
        return torch.stack(losses).mean() if losses else fs.sum() * 0.0


def supervoxel_draw_weight(ids: Tensor, radial_bins: int, angular_bins: int, height_bins: int) -> Tensor:
    """PVKD's difficulty-aware draw: each distinct supervoxel id's weight, its radial bin + 1 (far cells drawn more
    often), in the default float dtype.

    Read from the ids (:func:`~distilkit.losses.pvkd.supervoxel_radial_bin`), which gives bitwise the value of the
    earlier per-voxel maximum ``zeros(n).index_reduce_(0, inv, r_bin + 1, "amax", include_self=False)``: the voxels of a
    supervoxel share its radial bin. ``Tensor.index_reduce_`` has no deterministic CUDA implementation
    (``index_reduce_cuda`` is flagged whatever the reduction), and this needs no scatter at all."""
    return (supervoxel_radial_bin(ids, radial_bins, angular_bins, height_bins) + 1).to(torch.get_default_dtype())


class PVKD(PVKDCard, MultiTapObjective):
    """PVKD (Hou et al., CVPR 2022) as SCPNet Table 4 uses it: voxel-wise output KD plus inter-voxel
    affinity distillation inside supervoxels (the point-wise terms are dropped, as in SCPNet).

    Supervoxels are cells of a cylindrical partition (radius, azimuth, height) around the sensor
    at x = 0, y = centre. The affinity term is DSKD's relation gap inside each supervoxel, computed
    exactly with the Gram identity; with ``num_supervoxels`` a difficulty-aware sample favours far
    cells (probability proportional to radial bin + 1). The authors released no code
    (seed_code.md §6): coefficients and the number of supervoxels are this implementation's.
    Sparse alignment as DSKD (across grids: a coarser teacher read at the parent voxel, a finer one
    mean-pooled into the student's voxels); the logits must share one grid.
    """

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        p = self.params
        student: SparseVoxels = taps["student"]
        fs, ft, _ = aligned_pairs(student, taps["teacher"])
        groups, _ = supervoxel_ids(student.coords, student.spatial_shape, p.radial_bins, p.angular_bins,
                                   p.height_bins)
        chosen = None
        if p.num_supervoxels is not None:  # difficulty-aware: far cells are drawn more often
            ids = torch.unique(groups)
            if ids.numel() > p.num_supervoxels:
                weight = supervoxel_draw_weight(ids, p.radial_bins, p.angular_bins, p.height_bins)
                chosen = torch.multinomial(weight, p.num_supervoxels, replacement=False)
        return pvkd(fs, ft, groups, taps["student_logits"], taps["teacher_logits"], p.temperature,
                    voxel_mask(taps["target"], p.voxels, self.ignore_index), p.output_weight, p.affinity_weight, chosen)


__all__ = ["PKT", "PKTParams", "PVKD", "PVKDParams", "supervoxel_draw_weight"]
