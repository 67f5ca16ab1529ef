"""MonoOcc's distillation terms (Zheng et al., ICRA 2024, arXiv 2403.08766: a privileged branch — a large image
backbone and temporal frames — distilled into the monocular VoxFormer-style branch), as its release computes them
(ucaszyp/MonoOcc at 80a9247, ``projects/mmdet3d_plugin/MonoOcc/utils/ssc_loss.py``):

* :func:`monoocc_kl` — ``Distill_loss`` (L234-245, called from ``dense_heads/MonoOcc_head.py`` L436-439): the two
  models' voxel features (the head's 128-channel query volume, before its x2 upsampling to the label grid: "half
  resolution") at the voxels whose 2 x 2 x 2 block of labels holds a class (VoxFormer's downsampled labels, not 0
  nor 255), ``KLDivLoss(reduction="mean", log_target=True)(student, teacher)`` x2 (MonoOcc-L's ``ratio_distill``).
  The release applies it to the raw features (``form="raw"``): sum_{v,c} exp(t) (t - s) / (C n) — linear in the
  student, its gradient -exp(t) / (C n) whatever s is, no minimum at s = t, negative where the student's features
  exceed the teacher's. ``form="softmax"`` (distilkit's default) is the divergence the name says: each voxel's
  channels as a distribution, sum_{v,c} p_T (log p_T - log p_S) / (C n), p = softmax over the channels.
  The release assumes one sample (``squeeze()``, ``img_metas[0]``'s labels for the mask): here each sample has its
  own mask and mean, averaged over the batch (the same at B = 1); a sample without a masked voxel gives 0 (the
  release: NaN).
* :func:`monoocc_image` — ``cos_similarity_2d`` (L247-267): the teacher's image features resized to the student's
  (bilinear, ``align_corners=True``), 1 - the mean over all pixels of cos(f_S, f_T) over the channels, x2
  (``ratio_2d_distill``). Off in every released config (``use_large_model=False``; its teacher's features are not
  loaded), present in the code: the student's features pass an MLP 128 -> 256 -> 512 (ReLU after each) first.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

Form = Literal["softmax", "raw"]
FORMS = ("softmax", "raw")


def monoocc_kl(student_features: Tensor, teacher_features: Tensor, mask: Tensor, form: Form = "softmax") -> Tensor:
    """MonoOcc's voxel-feature distillation: the batch mean of each sample's sum over its masked voxels v and the C
    channels of the pointwise KLDivLoss term, / (C n_b). ``raw`` (the release): exp(t) (t - s) on the features as
    they are; ``softmax``: p_T (log p_T - log p_S), p the softmax over the channels. Features ``(B, C, *spatial)``,
    ``mask`` ``(B, *spatial)``."""
    if form not in FORMS:
        raise ValueError(f"monoocc_kl: form must be softmax or raw, got {form!r}")
    if student_features.shape != teacher_features.shape or mask.shape != student_features.shape[:1] + \
            student_features.shape[2:]:
        raise ValueError(f"monoocc_kl: features {tuple(student_features.shape)} and {tuple(teacher_features.shape)} "
                         f"must match, the mask {tuple(mask.shape)} be (B, *spatial)")
    s = student_features.flatten(2)
    t = teacher_features.to(s.dtype).flatten(2)
    if form == "softmax":
        s, t = torch.log_softmax(s, dim=1), torch.log_softmax(t, dim=1)
    pointwise = (t.exp() * (t - s)).sum(1)  # (B, N): KLDivLoss(log_target=True)'s terms summed over the channels
    keep = mask.flatten(1).bool()
    sums = torch.where(keep, pointwise, torch.zeros_like(pointwise)).sum(1)
    counts = keep.sum(1) * s.shape[1]
    return torch.where(counts > 0, sums / counts.clamp_min(1), sums * 0).mean()


def monoocc_image(student_features: Tensor, teacher_features: Tensor) -> Tensor:
    """MonoOcc's image-feature distillation: 1 - mean over the pixels of every image of cos(f_S, f_T) over the
    channels, the teacher's (B, C, h, w) resized to the student's (B, C, H, W) first (bilinear, corners aligned)."""
    if student_features.dim() != 4 or teacher_features.dim() != 4 or \
            student_features.shape[:2] != teacher_features.shape[:2]:
        raise ValueError(f"monoocc_image: features {tuple(student_features.shape)} and "
                         f"{tuple(teacher_features.shape)} must be (B, C, H, W) with one B and C (give the student "
                         "a connector to the teacher's channels)")
    teacher = teacher_features.to(student_features.dtype)
    if teacher.shape[2:] != student_features.shape[2:]:
        teacher = F.interpolate(teacher, size=tuple(student_features.shape[2:]), mode="bilinear", align_corners=True)
    return 1 - F.cosine_similarity(student_features, teacher, dim=1).mean()


__all__ = ["FORMS", "monoocc_image", "monoocc_kl"]
