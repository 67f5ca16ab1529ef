"""Output (logit) distillation: vanilla KD (Hinton et al. 2015) and DIST (Huang et al., NeurIPS 2022)."""

from __future__ import annotations

import torch
from torch import Tensor


def kd(student_logits: Tensor, teacher_logits: Tensor, temperature: float = 1.0, mask: Tensor | None = None) -> Tensor:
    """Vanilla KD: T^2 * mean over positions of KL(softmax(t/T) || softmax(s/T)).

    Logits are ``(B, K, *S)`` or (N, K), class dim 1; ``mask`` ``(B, *S)`` bool selects positions. The
    reduction is the per-position mean (never ``batchmean``), so the value does not grow with the
    grid size. 0 if no position is selected.
    """
    if student_logits.shape != teacher_logits.shape:
        raise ValueError(f"kd: student {tuple(student_logits.shape)} and teacher {tuple(teacher_logits.shape)} logits differ")
    if temperature <= 0:
        raise ValueError(f"kd: temperature must be > 0, got {temperature}")
    if mask is not None:
        expect = student_logits.shape[:1] + student_logits.shape[2:]
        if mask.shape != expect:
            raise ValueError(f"kd: mask must have shape {tuple(expect)} (logits without the class dim), got {tuple(mask.shape)}")
    log_ps = torch.log_softmax(student_logits / temperature, dim=1)
    log_pt = torch.log_softmax(teacher_logits.to(student_logits.dtype) / temperature, dim=1)
    kl = (log_pt.exp() * (log_pt - log_ps)).sum(1)  # (B, *S): one KL per position
    if mask is not None:
        kl = kl[mask.bool()]
    if kl.numel() == 0:
        return student_logits.sum() * 0.0
    return temperature**2 * kl.mean()


def kept_rows(x: Tensor, keep: Tensor) -> Tensor:
    """The (M, C) channel vectors of (B, C, *S) ``x`` at the M positions where ``keep`` (B, *S) holds, sample by
    sample in order: the masked positions gathered once, so that a term computes nothing at the others."""
    sample, position = keep.reshape(keep.shape[0], -1).nonzero(as_tuple=True)
    return x.flatten(2)[sample, :, position]


def per_sample_sums(values: Tensor, counts: Tensor) -> Tensor:
    """(B,) the sums of (M,) ``values`` over each sample's rows (rows in sample order, ``counts`` (B,) of them per
    sample, as :func:`kept_rows` gives them): each a pairwise ``sum``, as accurate as the mean over a full grid."""
    return torch.stack([part.sum() for part in values.split(counts.tolist())])


def kl_per_sample(student_logits: Tensor, teacher_logits: Tensor, keep: Tensor, temperature: float = 1.0) -> Tensor:
    """(B,) each sample's mean over its kept positions of KL(softmax(t/T) || softmax(s/T)) (0 where none is kept);
    logits (B, K, *S), ``keep`` (B, *S) bool. Only the kept positions are computed (gathered first: at a scene's
    occupied voxels, a few per cent of the grid). HASSC's and L2COcc's per-sample reductions are built on it."""
    keep = keep.bool()
    log_ps = torch.log_softmax(kept_rows(student_logits, keep) / temperature, dim=1)
    log_pt = torch.log_softmax(kept_rows(teacher_logits.to(student_logits.dtype), keep) / temperature, dim=1)
    kl = (log_pt.exp() * (log_pt - log_ps)).sum(1)  # (M,): one KL per kept position
    counts = keep.reshape(keep.shape[0], -1).sum(1)
    return per_sample_sums(kl, counts) / counts.clamp_min(1)  # a sample without a kept position sums nothing: 0


def pearson_rows(a: Tensor, b: Tensor, eps: float = 1e-8) -> Tensor:
    """Pearson correlation of matching rows: cosine of the mean-centred rows (eps in the denominator)."""
    a = a - a.mean(dim=1, keepdim=True)
    b = b - b.mean(dim=1, keepdim=True)
    return (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1) + eps)


def dist(student_logits: Tensor, teacher_logits: Tensor, beta: float = 1.0, gamma: float = 1.0,
         temperature: float = 1.0) -> Tensor:
    """DIST: T^2 (beta * (1 - mean_i pearson(p_s[i], p_t[i])) + gamma * (1 - mean_k pearson(p_s[:,k], p_t[:,k]))).

    (N, K) logits; p = softmax(logits / T) over classes. The inter-class term correlates each row's
    class distribution, the intra-class term each class's scores across the N rows. Scale-free:
    repeating the rows leaves the value unchanged. Handles N = 1 (the intra term is then 1).
    """
    if student_logits.dim() != 2 or student_logits.shape != teacher_logits.shape:
        raise ValueError(f"dist: expects equal (N, K) logits, got {tuple(student_logits.shape)} and {tuple(teacher_logits.shape)}")
    if student_logits.shape[0] == 0:
        return student_logits.sum() * 0.0
    ps = torch.softmax(student_logits / temperature, dim=1)
    pt = torch.softmax(teacher_logits.to(ps.dtype) / temperature, dim=1)
    inter = 1.0 - pearson_rows(ps, pt).mean()
    intra = 1.0 - pearson_rows(ps.T, pt.T).mean()
    return temperature**2 * (beta * inter + gamma * intra)
