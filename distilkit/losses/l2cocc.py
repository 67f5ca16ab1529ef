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
  per-sample means: the release's one sample per GPU gives the same value at B > 1). Exact, by square tiles of
  D = A - B (A = a a^T the student's cosines, B = b b^T the teacher's) with a hand-written backward: a tile is one
  GEMM, [a_I | b_I] [a_J | -b_J]^T = A_IJ - B_IJ; D is symmetric, so only the tiles I <= J are computed, those off
  the diagonal counted twice; each row of |D_IJ| is summed in the input's dtype, the row sums in float64. O(P^2 C)
  time, never a P x P matrix (at a 128 x 128 plane, P^2 = 2.7e8 entries, 1 GiB in float32 per matrix). The
  diagonal is 1 - 1 = 0 for every non-zero row whatever the features: its gradient is 0 here, where autograd of
  the dense form takes the sign of a rounding residue.

The release computes per-layer ratios for FSD (0.1, 1, 0.5, 1.5) and never uses them; its relation term reads the
first neck output of each of the three TPV planes and sums the three; the recipe's objectives choose the maps.
"""

from __future__ import annotations

import math
from typing import Literal, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd.function import once_differentiable

from distilkit.losses.logit import kept_rows, kl_per_sample, per_sample_sums

_ENTRIES = 1 << 24  # the most entries of one tile of the P x P matrix (64 MiB in float32)
_CPU_TILE = 1024  # the tiles' edge on the CPU (4 MiB in float32: a core's L2, between the GEMM and the next pass)


def _voxels(x: Tensor) -> Tensor:
    """(B, K, *spatial) -> (B, N, K)."""
    return x.flatten(2).transpose(1, 2)


def l2cocc_pad(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, include_empty: bool = False) -> Tensor:
    """L2COcc's prediction alignment: the batch mean of each sample's KL(p_T || p_S) averaged over its valid,
    non-empty voxels and the classes (see the module docstring). Logits ``(B, K, *spatial)``, labels
    ``(B, *spatial)``."""
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
    sums, counts = cosine_distance_sums(student_features, teacher_features, mask)
    if reduce == "pooled":
        sums, counts = sums.sum().reshape(1), counts.sum().reshape(1)
    return torch.where(counts > 0, sums / counts.clamp_min(1), sums * 0).mean()


def cosine_distance_sums(student_features: Tensor, teacher_features: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
    """(B,) each sample's sum of 1 - cos(f_S, f_T) (``F.cosine_similarity`` over the channels of (B, C, *spatial)
    maps) over the positions where ``mask`` (B, *spatial) holds, and (B,) their numbers. L2COcc's FSD and LiCROcc's
    CMRD average them."""
    keep = mask.bool()
    student = kept_rows(student_features, keep)
    teacher = kept_rows(teacher_features.to(student_features.dtype), keep)
    distance = 1 - F.cosine_similarity(student, teacher, dim=1)  # (M,): only the masked positions computed
    counts = keep.flatten(1).sum(1)
    return per_sample_sums(distance, counts), counts


def l2cocc_fsd(student_features: Tensor | Sequence[Tensor], teacher_features: Tensor | Sequence[Tensor],
               mask: Tensor | Sequence[Tensor], reduce: Reduce = "per_sample") -> Tensor:
    """L2COcc's numeric feature similarity: over the positions where ``mask`` ``(B, *spatial)`` holds, 1 - cos(f_S,
    f_T) over the channels of ``(B, C, *spatial)`` features, averaged per sample then over the batch (``per_sample``:
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
    """sum_b sum_ij |a_i.a_j - b_i.b_j| / (B P^2) over row-normalised (B, P, C) inputs, by square tiles of the
    P x P matrix D = A - B: tile (I, J) is one GEMM, [a_I | b_I] [a_J | -b_J]^T. D is symmetric, so only the tiles
    I <= J are computed, those off the diagonal counted twice."""

    @staticmethod
    def _tiles(p: int, device: torch.device) -> list[tuple[int, int, int, int, float]]:
        """(I start, I stop, J start, J stop, weight) of the tiles I <= J of a P x P matrix: edge sqrt(_ENTRIES),
        at most _CPU_TILE on the CPU (elsewhere fewer, larger GEMMs and launches)."""
        edge = max(1, min(p, math.isqrt(_ENTRIES), _CPU_TILE if device.type == "cpu" else p))
        starts = range(0, p, edge)
        return [(i, min(i + edge, p), j, min(j + edge, p), 1.0 if i == j else 2.0)
                for i in starts for j in starts if i <= j]

    @staticmethod
    def _tile(lhs: Tensor, rhs: Tensor, both: Tensor, i0: int, i1: int, j0: int, j1: int, out: Tensor) -> Tensor:
        """The tile (I, J) of D into ``out`` (a flat buffer): one GEMM; on a diagonal tile, D_ii = 1 - 1 = 0
        exactly where a_i and b_i are both non-zero."""
        d = torch.mm(lhs[i0:i1], rhs[j0:j1].T, out=out[:(i1 - i0) * (j1 - j0)].view(i1 - i0, j1 - j0))
        if i0 == j0:
            d.diagonal().masked_fill_(both[i0:i1], 0)
        return d

    @staticmethod
    def _operands(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """[a | b], [a | -b] (D = [a | b] [a | -b]^T) and the rows where a and b are both non-zero."""
        return torch.cat([a, b], 1), torch.cat([a, -b], 1), (a.abs().sum(1) > 0) & (b.abs().sum(1) > 0)

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor) -> Tensor:  # type: ignore[override]
        n, p = a.shape[0], a.shape[1]
        tiles = _RelationL1._tiles(p, a.device)
        buffer = a.new_empty(tiles[0][1] * tiles[0][3] if tiles else 0)  # the first tile is the largest
        rows = a.new_zeros(p, dtype=torch.float64)  # row sums of |D|, over the batch
        wide = None if a.dtype in (torch.float32, torch.float64) else torch.float32  # float16/bfloat16: sum in fp32
        for k in range(n):
            lhs, rhs, both = _RelationL1._operands(a[k], b[k])
            for i0, i1, j0, j1, weight in tiles:
                d = _RelationL1._tile(lhs, rhs, both, i0, i1, j0, j1, buffer)
                rows[i0:i1].add_(d.abs_().sum(1, dtype=wide), alpha=weight)  # = vector_norm(d, 1, 1): 7x faster (CPU)
        ctx.save_for_backward(a, b)
        return (rows.sum() / max(n * p * p, 1)).to(a.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        a, b = ctx.saved_tensors
        n, p, c = a.shape[0], a.shape[1], a.shape[2]
        need_a, need_b = ctx.needs_input_grad
        # dL/d[a | b] = (S + S^T) [a | -b] with S = sign(D): accumulate G = (S + S^T) [a | b] over the columns
        # wanted (a's, b's or both in one GEMM); b's gradient is -G's part
        cols = slice(0 if need_a else c, None if need_b else c)
        tiles = _RelationL1._tiles(p, a.device)
        buffer = a.new_empty(tiles[0][1] * tiles[0][3] if tiles else 0)  # the first tile is the largest
        g = a.new_zeros(n, p, (c if need_a else 0) + (b.shape[2] if need_b else 0))
        for k in range(n):
            lhs, rhs, both = _RelationL1._operands(a[k], b[k])
            m = lhs[:, cols]
            for i0, i1, j0, j1, weight in tiles:
                s = _RelationL1._tile(lhs, rhs, both, i0, i1, j0, j1, buffer).sign_()
                g[k, i0:i1].addmm_(s, m[j0:j1], alpha=weight)  # S_IJ [a_J | b_J] to the rows I
                g[k, j0:j1].addmm_(s.T, m[i0:i1], alpha=weight)  # S_IJ^T [a_I | b_I] to the rows J
        g *= grad / max(n * p * p, 1)
        return (g[..., :c] if need_a else None), ((-g[..., c:] if need_a else -g) if need_b else None)


def l2cocc_relation(student_features: Tensor, teacher_features: Tensor) -> Tensor:
    """L2COcc's relational feature similarity of one map: mean over the batch and the P^2 position pairs of
    ``|cos_S(i, j) - cos_T(i, j)|``, each model's cosines among its own P = prod(spatial) positions (channels may
    differ between the two). Exact, by tiles of the P x P matrices' difference: no P x P matrix is held."""
    if student_features.dim() < 3 or student_features.shape[0] != teacher_features.shape[0] or \
            student_features.shape[2:] != teacher_features.shape[2:]:
        raise ValueError(f"l2cocc_relation: features {tuple(student_features.shape)} and "
                         f"{tuple(teacher_features.shape)} must be (B, C, *spatial) with the same B and spatial size")
    a = F.normalize(_voxels(student_features), dim=2)
    b = F.normalize(_voxels(teacher_features.to(student_features.dtype)), dim=2)
    return _RelationL1.apply(a, b)


__all__ = ["REDUCTIONS", "cosine_distance_sums", "l2cocc_fsd", "l2cocc_pad", "l2cocc_relation"]
