"""L2COcc's distillation terms (Wang et al., IROS 2025: a frozen LiDAR teacher distilled into a camera student), as
its release computes them (``core/models/detectors/CameraSegmentor.py``): prediction alignment (PAD), feature
similarity numeric (FSD) and relational.

* :func:`l2cocc_pad` — per sample, ``KLDivLoss(reduction="mean")`` of the student's log-softmax against the
  teacher's softmax over the voxels that are valid (label != 255) and non-empty (label != 0; ``include_empty``:
  valid only, the release's ``distill_kl_empty``): sum_{v, k} p_T (log p_T - log p_S) / (n_v K); averaged over the
  batch (the release divides the sum over samples by the batch size: the mean of per-sample values, as its one
  sample per GPU under DDP). A sample without such voxels gives 0 (the release's mean over nothing is NaN).
* :func:`l2cocc_fsd` — the mean over the masked positions of 1 - cos(f_S, f_T) (``F.cosine_similarity``, channels
  the vector), per sample then over the batch (the release trains one sample per GPU: DDP averages the per-sample
  values) or pooled over the batch (``reduce="pooled"``: the release's code run at B > 1); 0 without a masked
  position (the release: NaN). Several maps: the mean over them (the release: the sum over its 20 maps divided by
  their number, then x4).
* :func:`l2cocc_relation` — per map, the P x P cosine-similarity matrices of the student with itself and of the
  teacher with itself (rows L2-normalised as ``F.normalize`` does: a zero row stays zero), their L1 distance averaged
  over the B P^2 entries (``F.l1_loss``; every sample has P^2 entries, so the pooled mean is the mean of the
  per-sample means: the release's one sample per GPU gives the same value at B > 1). Exact in row blocks with a
  hand-written backward: O(P^2 C) time, never a P x P matrix (at a 128 x 128 plane, P^2 = 2.7e8 entries, 1 GiB in
  float32 per matrix). The diagonal is |1 - 1|
  = 0 for every non-zero row whatever the features: its gradient is 0 here, where autograd of the dense form takes
  the sign of a rounding residue.

The release computes per-layer ratios for FSD (0.1, 1, 0.5, 1.5) and never uses them; its relation term reads the
first neck output of each of the three TPV planes and sums the three; the recipe's objectives choose the maps.
"""

from __future__ import annotations

from typing import Literal, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.losses.logit import kl_per_sample

_ENTRIES = 1 << 24  # entries of one row block of the P x P matrices (64 MiB in float32)


def _voxels(x: Tensor) -> Tensor:
    """(B, K, *spatial) -> (B, N, K)."""
    return x.flatten(2).transpose(1, 2)


def l2cocc_pad(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, include_empty: bool = False) -> Tensor:
    """L2COcc's prediction alignment: the batch mean of each sample's KL(p_T || p_S) averaged over its valid,
    non-empty voxels and the classes (see the module docstring). Logits (B, K, *spatial), labels (B, *spatial)."""
    if student_logits.shape != teacher_logits.shape or labels.shape != student_logits.shape[:1] + \
            student_logits.shape[2:]:
        raise ValueError(f"l2cocc_pad: student {tuple(student_logits.shape)}, teacher {tuple(teacher_logits.shape)} "
                         f"and labels {tuple(labels.shape)} must be (B, K, *spatial) twice and (B, *spatial)")
    keep = (labels != 255) if include_empty else (labels != 255) & (labels != 0)
    per_sample = kl_per_sample(student_logits, teacher_logits, keep) / student_logits.shape[1]  # KLDivLoss: / K too
    return per_sample.mean()


Reduce = Literal["per_sample", "pooled"]
REDUCTIONS = ("per_sample", "pooled")


def _fsd_map(student_features: Tensor, teacher_features: Tensor, mask: Tensor, reduce: str) -> Tensor:
    """One map's 1 - cos over its masked positions: the mean of each sample's mean (``per_sample``) or the mean
    over the batch's masked positions pooled (``pooled``); 0 for a sample (batch) without one."""
    if student_features.shape != teacher_features.shape or mask.shape != student_features.shape[:1] + \
            student_features.shape[2:]:
        raise ValueError(f"l2cocc_fsd: features {tuple(student_features.shape)} and {tuple(teacher_features.shape)} "
                         f"must match, the mask {tuple(mask.shape)} be (B, *spatial)")
    keep = mask.flatten(1).bool()
    distance = 1 - F.cosine_similarity(student_features, teacher_features.to(student_features.dtype), dim=1)
    distance = torch.where(keep, distance.flatten(1), torch.zeros_like(distance.flatten(1)))
    if reduce == "pooled":
        sums, counts = distance.sum().reshape(1), keep.sum().reshape(1)
    else:
        sums, counts = distance.sum(1), keep.sum(1)
    return torch.where(counts > 0, sums / counts.clamp_min(1), sums * 0).mean()


def l2cocc_fsd(student_features: Tensor | Sequence[Tensor], teacher_features: Tensor | Sequence[Tensor],
               mask: Tensor | Sequence[Tensor], reduce: Reduce = "per_sample") -> Tensor:
    """L2COcc's numeric feature similarity: over the positions where ``mask`` (B, *spatial) holds, 1 - cos(f_S,
    f_T) over the channels of (B, C, *spatial) features, averaged per sample then over the batch (``per_sample``:
    the release, one sample per GPU) or over the batch's positions pooled (``pooled``: the release's code at B > 1
    on one GPU). Sequences of maps (each pair of one shape, with its own mask): the mean over the maps — the
    release sums over its maps and divides by their number before its weight 4."""
    if reduce not in REDUCTIONS:
        raise ValueError(f"l2cocc_fsd: reduce must be per_sample or pooled, got {reduce!r}")
    if isinstance(student_features, Tensor):
        if not isinstance(teacher_features, Tensor) or not isinstance(mask, Tensor):
            raise ValueError("l2cocc_fsd: one student map needs one teacher map and one mask")
        return _fsd_map(student_features, teacher_features, mask, reduce)
    maps = list(zip(student_features, teacher_features, mask))
    if not maps or not len(maps) == len(student_features) == len(teacher_features) == len(mask):
        raise ValueError(f"l2cocc_fsd: needs as many teacher maps and masks as student maps, at least one (got "
                         f"{len(student_features)}, {len(teacher_features)} and {len(mask)})")
    return torch.stack([_fsd_map(s, t, m, reduce) for s, t, m in maps]).mean()


class _RelationL1(torch.autograd.Function):
    """sum_b sum_ij |a_i.a_j - b_i.b_j| / (B P^2) over row-normalised (B, P, C) inputs, one row block at a time."""

    @staticmethod
    def _block(a: Tensor, b: Tensor, start: int, stop: int) -> Tensor:
        d = a[start:stop] @ a.T - b[start:stop] @ b.T
        rows = torch.arange(start, stop, device=a.device)
        both = (a[start:stop].abs().sum(1) > 0) & (b[start:stop].abs().sum(1) > 0)  # the diagonal is exactly 0
        d[rows - start, rows] = torch.where(both, torch.zeros_like(d[rows - start, rows]), d[rows - start, rows])
        return d

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor) -> Tensor:  # type: ignore[override]
        n, p = a.shape[0], a.shape[1]
        step = max(1, _ENTRIES // max(p, 1))
        total = a.new_zeros((), dtype=torch.float64)
        for i in range(n):
            for start in range(0, p, step):
                total += _RelationL1._block(a[i], b[i], start, min(start + step, p)).abs().sum(dtype=torch.float64)
        ctx.save_for_backward(a, b)
        ctx.step = step
        return (total / max(n * p * p, 1)).to(a.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        a, b = ctx.saved_tensors
        n, p, step = a.shape[0], a.shape[1], ctx.step
        need_a, need_b = ctx.needs_input_grad
        ga = torch.zeros_like(a) if need_a else None
        gb = torch.zeros_like(b) if need_b else None
        for i in range(n):
            for start in range(0, p, step):
                stop = min(start + step, p)
                s = _RelationL1._block(a[i], b[i], start, stop).sign()  # d|A - B| / dA for this block of rows
                if ga is not None:  # A = a a^T: dL/da = (S + S^T) a, a block of rows of S at a time
                    ga[i, start:stop] += s @ a[i]
                    ga[i] += s.T @ a[i, start:stop]
                if gb is not None:
                    gb[i, start:stop] -= s @ b[i]
                    gb[i] -= s.T @ b[i, start:stop]
        scale = grad / max(n * p * p, 1)
        return (ga * scale if ga is not None else None), (gb * scale if gb is not None else None)


def l2cocc_relation(student_features: Tensor, teacher_features: Tensor) -> Tensor:
    """L2COcc's relational feature similarity of one map: mean over the batch and the P^2 position pairs of
    |cos_S(i, j) - cos_T(i, j)|, each model's cosines among its own P = prod(spatial) positions (channels may
    differ between the two). Exact, in row blocks: no P x P matrix is held."""
    if student_features.dim() < 3 or student_features.shape[0] != teacher_features.shape[0] or \
            student_features.shape[2:] != teacher_features.shape[2:]:
        raise ValueError(f"l2cocc_relation: features {tuple(student_features.shape)} and "
                         f"{tuple(teacher_features.shape)} must be (B, C, *spatial) with the same B and spatial size")
    a = F.normalize(_voxels(student_features), dim=2)
    b = F.normalize(_voxels(teacher_features.to(student_features.dtype)), dim=2)
    return _RelationL1.apply(a, b)


__all__ = ["REDUCTIONS", "l2cocc_fsd", "l2cocc_pad", "l2cocc_relation"]
