"""CleanerS (Wang et al., CVPR 2023; a Scribble2Scene Table 5 baseline): semantic-centre and semantic-affinity
distillation over class centres, as the authors' code computes them (seed_code.md §2.3)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.losses.feature import fitnet
from distilkit.losses.rgo2d import _gsl, centre_affinity


def cleaners(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, temperature: float = 1.0,
             kd_sc: float = 1.0, kd_sa: float = 1.0, ignore_index: int = 255, student_features: Tensor | None = None,
             teacher_features: Tensor | None = None, kd_t: float = 1.0) -> Tensor:
    """CleanerS: ``kd_sc · KD-SC + kd_sa · KD-SA`` averaged over the samples that have a labelled voxel, plus
    ``kd_t · KD-T`` with a feature pair.

    Per sample, over the voxels whose label is not ``ignore_index``: the class centres G are the mean logits of
    the voxels of each class present (labels != 0). KD-SC = T² mean_c KL(softmax(G_t,c/T) ‖ softmax(G_s,c/T));
    KD-SA = MSE between each voxel's cosine similarity to every centre, student vs teacher (all non-ignored
    voxels, labelled or not). KD-T = MSE(F_s, F_t) of equal-shaped feature maps.

    Args:
        student_logits, teacher_logits: ``(B, K, *S)`` logits.
        labels: ``(B, *S)`` integer labels (0 = empty, ``ignore_index`` = never used).
    """
    if student_logits.shape != teacher_logits.shape or student_logits.dim() < 3:
        raise ValueError(f"cleaners: expects equal (B, K, *S) logits, got {tuple(student_logits.shape)} and "
                         f"{tuple(teacher_logits.shape)}")
    expect = student_logits.shape[:1] + student_logits.shape[2:]
    if labels.shape != expect:
        raise ValueError(f"cleaners: labels {tuple(labels.shape)} must be {tuple(expect)}")
    if temperature <= 0:
        raise ValueError(f"cleaners: temperature must be > 0, got {temperature}")
    zero = student_logits.sum() * 0.0
    sc, sa, n = zero, zero, 0
    for i in range(student_logits.shape[0]):
        valid = (labels[i] != ignore_index).reshape(-1)
        ys = student_logits[i].flatten(1).T[valid]
        yt = teacher_logits[i].flatten(1).T[valid].to(ys.dtype)
        lab = labels[i].reshape(-1)[valid]
        sel = lab != 0
        if not bool(sel.any()):
            continue
        classes, inv = torch.unique(lab[sel], return_inverse=True)
        gs, gt = _gsl(ys[sel], inv, classes.numel()), _gsl(yt[sel], inv, classes.numel())
        log_ps = torch.log_softmax(gs / temperature, 1)
        log_pt = torch.log_softmax(gt / temperature, 1)
        sc = sc + temperature**2 * (log_pt.exp() * (log_pt - log_ps)).sum(1).mean()
        sa = sa + F.mse_loss(centre_affinity(ys, gs), centre_affinity(yt, gt))
        n += 1
    total = (kd_sc * sc + kd_sa * sa) / max(n, 1)
    if (student_features is None) != (teacher_features is None):
        raise ValueError("cleaners: give both student_features and teacher_features, or neither")
    if student_features is not None and teacher_features is not None:
        total = total + kd_t * fitnet(student_features, teacher_features)
    return total
