"""Dense-to-Sparse Knowledge Distillation (SCPNet, Xia et al. CVPR 2023, eq. 1-2).

With row-normalised features A = F_S/||F_S|| and B = F_T/||F_T|| (N x C), eq. 1 gives the
relation matrices P_S = A A^T and P_T = B B^T, and eq. 2 is

    L = 1/N^2 * sum_ij (P_S(i,j) - P_T(i,j))^2 = ||A A^T - B B^T||_F^2 / N^2.

The Frobenius identity ||A A^T - B B^T||_F^2 = ||A^T A||_F^2 + ||B^T B||_F^2 - 2 ||A^T B||_F^2
makes this exact in O(N C^2) time and O(N C + C^2) memory: no N x N matrix is formed. The three
C x C Gram products are accumulated in float64 over row blocks, so the value stays accurate
(each term is O(N^2), their difference may be small) at millions of voxels.
A zero row (e.g. a voxel the teacher does not have) normalises to zero: its cosine
similarity with every voxel is defined as 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

_BLOCK = 1 << 17  # rows per float64 block: bounds the float64 working set to BLOCK x C


def normalize_rows(x: Tensor) -> Tensor:
    """Row-wise L2 normalisation; an all-zero row stays zero (and gets zero gradient)."""
    norm = torch.linalg.vector_norm(x, dim=1, keepdim=True)
    nonzero = norm > 0
    inv = torch.where(nonzero, 1.0 / norm.clamp_min(torch.finfo(x.dtype).tiny), torch.zeros_like(norm))
    return x * inv


def _grams(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    c_a, c_b = a.shape[1], b.shape[1]
    gaa = a.new_zeros((c_a, c_a), dtype=torch.float64)
    gbb = a.new_zeros((c_b, c_b), dtype=torch.float64)
    gab = a.new_zeros((c_a, c_b), dtype=torch.float64)
    for start in range(0, a.shape[0], _BLOCK):
        ab = a[start:start + _BLOCK].double()
        bb = b[start:start + _BLOCK].double()
        gaa += ab.T @ ab
        gbb += bb.T @ bb
        gab += ab.T @ bb
    return gaa, gbb, gab


class _RelationGap(torch.autograd.Function):
    """||A A^T - B B^T||_F^2 / N^2 for already-normalised A, B via C x C Gram matrices."""

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor) -> Tensor:  # type: ignore[override]
        n = a.shape[0]
        gaa, gbb, gab = _grams(a, b)
        value = (gaa.square().sum() + gbb.square().sum() - 2.0 * gab.square().sum()) / float(n) ** 2
        ctx.save_for_backward(a, b, gaa, gbb, gab)
        return value.to(a.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        a, b, gaa, gbb, gab = ctx.saved_tensors
        n = a.shape[0]
        scale = grad.double() * 4.0 / float(n) ** 2
        need_a, need_b = ctx.needs_input_grad
        grad_a = torch.empty_like(a) if need_a else None
        grad_b = torch.empty_like(b) if need_b else None
        for start in range(0, n, _BLOCK):
            ab = a[start:start + _BLOCK].double()
            bb = b[start:start + _BLOCK].double()
            if grad_a is not None:  # d/dA = 4/N^2 (A A^T A - B B^T A)
                grad_a[start:start + _BLOCK] = (scale * (ab @ gaa - bb @ gab.T)).to(a.dtype)
            if grad_b is not None:  # d/dB = 4/N^2 (B B^T B - A A^T B)
                grad_b[start:start + _BLOCK] = (scale * (bb @ gbb - ab @ gab)).to(b.dtype)
        return grad_a, grad_b


def dskd(student: Tensor, teacher: Tensor) -> Tensor:
    """DSKD relational loss, SCPNet eq. 1-2, exact and without an N x N matrix.

    Args:
        student: (N, C_s) voxel features of the student.
        teacher: (N, C_t) teacher features of the *same* N voxels (row i describes the
            same voxel in both; see :func:`distilkit.geometry.align_sparse`). C_s may differ
            from C_t, since only cosine similarities between rows are compared.

    Returns:
        Scalar: the mean over all N^2 voxel pairs of (cos_S(i,j) - cos_T(i,j))^2.
        0 for N = 0. Differentiable with respect to both inputs.
    """
    if student.dim() != 2 or teacher.dim() != 2:
        raise ValueError(f"dskd expects (N, C) tensors, got student {tuple(student.shape)} and teacher {tuple(teacher.shape)}")
    if student.shape[0] != teacher.shape[0]:
        raise ValueError(
            f"dskd: student and teacher must describe the same N voxels, got N={student.shape[0]} "
            f"and N={teacher.shape[0]} (align them first with distilkit.geometry.align_sparse)"
        )
    if student.shape[0] == 0:
        return student.sum() * 0.0 + teacher.sum() * 0.0
    teacher = teacher.to(student.dtype)
    return _RelationGap.apply(normalize_rows(student), normalize_rows(teacher))
