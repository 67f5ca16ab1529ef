"""PVKD (Hou et al., CVPR 2022) as SCPNet's Table 4 uses it: voxel-wise output KD plus inter-voxel affinity
distillation inside cylindrical supervoxels (the point-wise terms dropped, as in SCPNet). The authors released
no code (seed_code.md §6): the partition and the coefficients are this implementation's."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from distilkit.losses.dskd import dskd
from distilkit.losses.logit import kd


def supervoxel_ids(coords: Tensor, shape: tuple[int, int, int], radial_bins: int = 8, angular_bins: int = 8,
                   height_bins: int = 2) -> tuple[Tensor, Tensor]:
    """Each voxel's supervoxel (a cell of a cylindrical partition around the sensor at x = 0, y = Y/2, distinct
    per sample) and its radial bin. ``coords``: (N, 4) int (batch, x, y, z) on a grid of ``shape`` (X, Y, Z)."""
    x, y, z = shape
    cx = coords[:, 1].float() + 0.5
    cy = coords[:, 2].float() + 0.5 - y / 2
    r = torch.sqrt(cx**2 + cy**2)
    r_bin = (r / math.hypot(x, y / 2) * radial_bins).long().clamp(0, radial_bins - 1)
    a_bin = ((torch.atan2(cy, cx) + math.pi / 2) / math.pi * angular_bins).long().clamp(0, angular_bins - 1)
    z_bin = (coords[:, 3] * height_bins // z).clamp(0, height_bins - 1)
    cell = (r_bin * angular_bins + a_bin) * height_bins + z_bin
    return coords[:, 0] * (radial_bins * angular_bins * height_bins) + cell, r_bin


def supervoxel_radial_bin(ids: Tensor, radial_bins: int = 8, angular_bins: int = 8, height_bins: int = 2) -> Tensor:
    """The radial bin of each supervoxel id of :func:`supervoxel_ids` (made with the same bin counts), read from the
    id itself: every voxel of a supervoxel shares its cell, hence its radial bin."""
    return ids % (radial_bins * angular_bins * height_bins) // (angular_bins * height_bins)


def pvkd_affinity(student: Tensor, teacher: Tensor, groups: Tensor, chosen: Tensor | None = None) -> Tensor:
    """Mean over supervoxels of DSKD's relation gap inside each: mean_g ‖Â_g Â_gᵀ − B̂_g B̂_gᵀ‖² / n_g²
    (exact, by the Gram identity, no n_g × n_g matrix).

    Args:
        student, teacher: (N, C_s), (N, C_t) features of the same N voxels.
        groups: (N,) supervoxel id of each voxel.
        chosen: indices into the sorted distinct ids of the supervoxels to average over (default: all).
    """
    if student.shape[0] != teacher.shape[0] or groups.shape != student.shape[:1]:
        raise ValueError(f"pvkd: student {tuple(student.shape)}, teacher {tuple(teacher.shape)} and groups "
                         f"{tuple(groups.shape)} must describe the same N voxels")
    ids, inv = torch.unique(groups, return_inverse=True)
    if chosen is None:
        chosen = torch.arange(ids.numel(), device=ids.device)
    order = torch.argsort(inv)
    counts = torch.bincount(inv, minlength=ids.numel())
    starts = torch.cumsum(counts, 0) - counts
    aff = [dskd(student[order[s:s + c]], teacher[order[s:s + c]])
           for s, c in zip(starts[chosen].tolist(), counts[chosen].tolist())]
    return torch.stack(aff).mean() if aff else student.sum() * 0.0


def pvkd(student: Tensor, teacher: Tensor, groups: Tensor, student_logits: Tensor, teacher_logits: Tensor,
         temperature: float = 1.0, mask: Tensor | None = None, output_weight: float = 1.0,
         affinity_weight: float = 100.0, chosen: Tensor | None = None) -> Tensor:
    """PVKD: ``output_weight · KD(logits) + affinity_weight · pvkd_affinity(features, groups)``.

    Args:
        student, teacher: (N, C) aligned voxel features; groups: (N,) supervoxel ids (:func:`supervoxel_ids`).
        student_logits, teacher_logits: ``(B, K, *S)`` logits; ``mask`` ``(B, *S)`` bool selects the KD voxels.
    """
    out = kd(student_logits, teacher_logits, temperature, mask)
    return output_weight * out + affinity_weight * pvkd_affinity(student, teacher, groups, chosen)
