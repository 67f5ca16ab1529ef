"""LiCROcc's distillation terms (Ma et al., RA-L 2025, arXiv 2407.16197: a LiDAR + camera fusion teacher distilled
into a radar or radar + camera student on BEV), as its release computes them (HR-zju/LiCROcc at 0c1423b,
``projects/mmdet3d_plugin/ssc_rs/detectors/ssc_rs.py``). The paper names three modules; the release's flags:

* :func:`licrocc_kl` — PDD (``Distill_1``, L403-422, L561-571): per sample, ``KLDivLoss(reduction="mean")`` of the
  student's log-softmax against the teacher's softmax over the classes, at the voxels whose label is neither empty
  (0) nor ignored (255): sum_{v,k} p_T (log p_T - log p_S) / (n_v K); times the sample's scene weight; averaged
  over the batch (the release: the sum over samples / B). A sample without such a voxel gives 0 (the release: NaN).
* :func:`licrocc_bev` — CMRD (``Distill_2``, L500-536): per sample and BEV map, the mean of 1 - cos(f_S, f_T)
  (channels the vector) over the BEV cells whose column holds an occupied voxel; times the scene weight; averaged
  over the maps and the samples (the release: the sum over 3 maps x B samples / 3B, then its hard-coded x4).
* :func:`licrocc_affinity` — BRD (``Distill_3``, L540-558, ``calculate_cosine_similarity`` L424-438): each map
  of both models resized to ``size`` (bilinear, ``align_corners=False``; the release: the student's last map,
  32 x 32), each model's P x P cosine matrix among its own cells, the L1 mean over the B P^2 entries; summed over
  the maps (the release: maps x3_f, x4_f, x5; x ratio_distill 10 x 4 = 40). The release divides the batch mean by
  B a second time (``release_batch=True``): its weight is 40 / B per sample (B = 4 per GPU in its configs).

The scene weight (``scene_weights``, (B,)) is the release's 1e-5 for a scene its dataset calls not useful (night or
rain): its dataset sets every scene useful (L335), so its weights are all 1. The paper's equations were not
available to us (the stored copy holds the abstract): the defaults follow the release except where its code is
an evident slip (the CMRD mask applied transposed, :data:`distilkit.objectives.licrocc`'s ``transpose_mask``).
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.losses.l2cocc import cosine_distance_sums, l2cocc_relation
from distilkit.losses.logit import kl_per_sample


def _scene_weights(weights: Tensor | None, batch: int, like: Tensor) -> Tensor:
    if weights is None:
        return like.new_ones(batch)
    if weights.shape != (batch,):
        raise ValueError(f"licrocc: scene_weights must be (B,) = ({batch},), got {tuple(weights.shape)}")
    return weights.to(like.dtype)


def licrocc_kl(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor,
               scene_weights: Tensor | None = None) -> Tensor:
    """LiCROcc's PDD: the batch mean of w_b KL(p_T || p_S) averaged over sample b's voxels with a class label (not
    0, not 255) and over the K classes. Logits ``(B, K, *spatial)``, labels ``(B, *spatial)``, ``scene_weights``
    (B,)."""
    if student_logits.shape != teacher_logits.shape or labels.shape != student_logits.shape[:1] + \
            student_logits.shape[2:]:
        raise ValueError(f"licrocc_kl: student {tuple(student_logits.shape)}, teacher {tuple(teacher_logits.shape)} "
                         f"and labels {tuple(labels.shape)} must be (B, K, *spatial) twice and (B, *spatial)")
    keep = (labels != 255) & (labels != 0)
    per_sample = kl_per_sample(student_logits, teacher_logits, keep) / student_logits.shape[1]  # KLDivLoss: / K too
    return (per_sample * _scene_weights(scene_weights, len(per_sample), per_sample)).mean()


def licrocc_bev(student_maps: Sequence[Tensor], teacher_maps: Sequence[Tensor], masks: Sequence[Tensor],
                scene_weights: Tensor | None = None) -> Tensor:
    """LiCROcc's CMRD: the mean over the maps m and samples b of w_b times sample b's mean of 1 - cos(f_S, f_T) over
    the cells where ``masks[m]`` (B, H, W) holds (0 for a sample without one). Maps (B, C, H, W), each pair of one
    shape (the student's residual and the teacher's fused feature in the release)."""
    maps = list(zip(student_maps, teacher_maps, masks))
    if not maps or not len(maps) == len(student_maps) == len(teacher_maps) == len(masks):
        raise ValueError(f"licrocc_bev: needs as many teacher maps and masks as student maps, at least one (got "
                         f"{len(student_maps)}, {len(teacher_maps)} and {len(masks)})")
    per_map = []
    for s, t, m in maps:
        if s.shape != t.shape or m.shape != s.shape[:1] + s.shape[2:]:
            raise ValueError(f"licrocc_bev: maps {tuple(s.shape)} and {tuple(t.shape)} must match, the mask "
                             f"{tuple(m.shape)} be (B, *spatial)")
        sums, counts = cosine_distance_sums(s, t, m)
        means = torch.where(counts > 0, sums / counts.clamp_min(1), sums * 0)
        per_map.append(means * _scene_weights(scene_weights, len(means), means))
    return torch.stack(per_map).mean()


def licrocc_affinity(student_maps: Sequence[Tensor], teacher_maps: Sequence[Tensor],
                     size: tuple[int, int] | None = (32, 32), release_batch: bool = False) -> Tensor:
    """LiCROcc's BRD: the sum over the maps of mean_{b,i,j} ``|cos_S(i, j) - cos_T(i, j)|``, each model's cosines among
    its own P cells of the map resized to ``size`` (bilinear, ``align_corners=False``; None: as they are, P = H W,
    computed in tiles without a P x P matrix). ``release_batch``: each map's mean divided by B again (the release).
    Maps (B, C, H, W); the two models' channels may differ."""
    if not student_maps or len(student_maps) != len(teacher_maps):
        raise ValueError(f"licrocc_affinity: needs as many teacher maps as student maps, at least one (got "
                         f"{len(student_maps)} and {len(teacher_maps)})")
    total = None
    for s, t in zip(student_maps, teacher_maps):
        if s.dim() != 4 or t.dim() != 4 or s.shape[0] != t.shape[0]:
            raise ValueError(f"licrocc_affinity: maps must be (B, C, H, W) with one B, got {tuple(s.shape)} and "
                             f"{tuple(t.shape)}")
        if size is not None:
            s = F.interpolate(s, size=tuple(size), mode="bilinear", align_corners=False)
            t = F.interpolate(t.to(s.dtype), size=tuple(size), mode="bilinear", align_corners=False)
        elif s.shape[2:] != t.shape[2:]:
            raise ValueError(f"licrocc_affinity: maps {tuple(s.shape)} and {tuple(t.shape)} differ in size: give a "
                             "size to resize both to")
        term = l2cocc_relation(s, t)
        term = term / s.shape[0] if release_batch else term
        total = term if total is None else total + term
    return total


__all__ = ["licrocc_affinity", "licrocc_bev", "licrocc_kl"]
