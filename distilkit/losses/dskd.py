"""Dense-to-Sparse Knowledge Distillation (SCPNet, Xia et al. CVPR 2023, eq. 1-2).

With row-normalised features A = F_S/||F_S|| and B = F_T/||F_T|| (N x C), eq. 1 gives the
relation matrices P_S = A A^T and P_T = B B^T, and eq. 2 is

    L = 1/N^2 * sum_ij (P_S(i,j) - P_T(i,j))^2 = ||A A^T - B B^T||_F^2 / N^2.

The Frobenius identity ||A A^T - B B^T||_F^2 = ||A^T A||_F^2 + ||B^T B||_F^2 - 2 ||A^T B||_F^2
makes this exact in O(N C^2) time and O(N C + C^2) memory: no N x N matrix is formed. With equal
widths the same number is computed from S = A + B and D = A - B (see :class:`_RelationGap`),
which does not cancel large terms when the student is close to the teacher. The C x C Gram
products are computed per row block in the input precision (float32: fast matrix units) and
summed over blocks in float64; ``distilkit bench dskd`` reports the error against float64.
A zero row (e.g. a voxel the teacher does not have) normalises to zero: its cosine
similarity with every voxel is defined as 0.
"""

from __future__ import annotations

import torch
from torch import Tensor

_BLOCK = 1 << 14  # rows per block: float32 Gram products of a block are exact enough to sum in float64


def normalize_rows(x: Tensor) -> Tensor:
    """Row-wise L2 normalisation; an all-zero row stays zero (and gets zero gradient)."""
    norm = torch.linalg.vector_norm(x, dim=1, keepdim=True)
    nonzero = norm > 0
    inv = torch.where(nonzero, 1.0 / norm.clamp_min(torch.finfo(x.dtype).tiny), torch.zeros_like(norm))
    return x * inv


def _unit(x: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised rows and 1/||row|| (0 for a zero row)."""
    norm = torch.linalg.vector_norm(x, dim=1, keepdim=True)
    inv = torch.where(norm > 0, 1.0 / norm.clamp_min(torch.finfo(x.dtype).tiny), torch.zeros_like(norm))
    return x * inv, inv


def _block_units(s: Tensor, t: Tensor, start: int, sd: bool) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One row block: (A, B) normalised, or (S = A + B, D = A - B) when ``sd``; plus 1/||row|| of each input."""
    a, inv_a = _unit(s[start:start + _BLOCK])
    b, inv_b = _unit(t[start:start + _BLOCK])
    if sd:
        return a + b, a - b, inv_a, inv_b
    return a, b, inv_a, inv_b


def _grams(s: Tensor, t: Tensor, sd: bool) -> tuple[Tensor, Tensor, Tensor]:
    """X^T X, Y^T Y, Y^T X over all rows for (X, Y) = (A, B), or (S, D) when ``sd``: each block's
    products in the input precision (float32 on the fast path), summed over blocks in float64."""
    c_a, c_b = s.shape[1], t.shape[1]
    gxx = s.new_zeros((c_a, c_a), dtype=torch.float64)
    gyy = s.new_zeros((c_b, c_b), dtype=torch.float64)
    gyx = s.new_zeros((c_b, c_a), dtype=torch.float64)
    for start in range(0, s.shape[0], _BLOCK):
        x, y, _, _ = _block_units(s, t, start, sd)
        gxx += (x.T @ x).double()
        gyy += (y.T @ y).double()
        gyx += (y.T @ x).double()
    return gxx, gyy, gyx


class _RelationGap(torch.autograd.Function):
    """||A A^T - B B^T||_F^2 / N^2 with A, B the row-normalised inputs, via C x C Gram matrices.

    Equal widths use S = A + B, D = A - B: A A^T - B B^T = (S D^T + D S^T) / 2, so
    N^2 L = (tr(G_SS G_DD) + tr(G_DS G_DS)) / 2 -- no cancellation of large terms when the student
    is close to the teacher (float32 blocks stay accurate). Other widths use
    N^2 L = ||A^T A||^2 + ||B^T B||^2 - 2 ||A^T B||^2. Normalisation is fused into the blocks and
    recomputed in the backward pass, so no normalised copy of the inputs is kept.
    """

    @staticmethod
    def forward(ctx, s: Tensor, t: Tensor) -> Tensor:  # type: ignore[override]
        n = s.shape[0]
        sd = s.shape[1] == t.shape[1]
        gxx, gyy, gyx = _grams(s, t, sd)
        if sd:
            value = 0.5 * ((gxx * gyy).sum() + (gyx * gyx.T).sum()) / float(n) ** 2
        else:
            value = (gxx.square().sum() + gyy.square().sum() - 2.0 * gyx.square().sum()) / float(n) ** 2
        ctx.sd = sd
        ctx.save_for_backward(s, t, gxx, gyy, gyx)
        return value.to(s.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None]:  # type: ignore[override]
        s, t, gxx, gyy, gyx = ctx.saved_tensors
        n = s.shape[0]
        scale = float(grad) / float(n) ** 2
        need_s, need_t = ctx.needs_input_grad
        # dL/dA = 4/N^2 (A A^T - B B^T) A, dL/dB = -4/N^2 (A A^T - B B^T) B, written as
        # dL/dA = A P + B Q and dL/dB = A R + B T with C x C matrices (float64, then cast):
        if ctx.sd:  # = 2/N^2 (S D^T A + D S^T A), D^T A = (G_DS + G_DD)/2, S^T A = (G_SS + G_SD)/2, ...
            m0, m1, m2, m3 = (scale * g for g in (gyx + gyy, gxx + gyx.T, gyx - gyy, gxx - gyx.T))
            # with X = A + B, Y = A - B: dL/dA = X m0 + Y m1, dL/dB = -(X m2 + Y m3)
            mats = (m0 + m1, m0 - m1, -(m2 + m3), m3 - m2)
        else:  # = 4/N^2 (A G_AA - B G_AB^T), 4/N^2 (B G_BB - A G_AB)
            mats = (4.0 * scale * gxx, -4.0 * scale * gyx, -4.0 * scale * gyx.T, 4.0 * scale * gyy)
        p, q, r, u = (m.to(s.dtype) for m in mats)
        grad_s = torch.empty_like(s) if need_s else None
        grad_t = torch.empty_like(t) if need_t else None
        for start in range(0, n, _BLOCK):
            sl = slice(start, start + _BLOCK)
            a, inv_a = _unit(s[sl])
            b, inv_b = _unit(t[sl])
            for out, unit, inv, first, second in ((grad_s, a, inv_a, p, q), (grad_t, b, inv_b, r, u)):
                if out is None:
                    continue
                g = torch.mm(a, first, out=out[sl]).addmm_(b, second)
                # through unit = x / ||x||: d/dx = (g - unit <unit, g>) / ||x||
                dot = torch.linalg.vecdot(unit, g, dim=1).unsqueeze(1)
                g.addcmul_(unit, dot, value=-1.0).mul_(inv)
        return grad_s, grad_t


def dskd(student: Tensor, teacher: Tensor) -> Tensor:
    """DSKD relational loss, SCPNet eq. 1-2, exact and without an N x N matrix.

    Args:
        student: (N, C_s) voxel features of the student.
        teacher: (N, C_t) teacher features of the *same* N voxels (row i describes the
            same voxel in both; see ``distilkit.geometry.align_sparse``). C_s may differ
            from C_t, since only cosine similarities between rows are compared.

    Returns:
        The mean over all N^2 voxel pairs of (cos_S(i,j) - cos_T(i,j))^2.
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
    return _RelationGap.apply(student, teacher)
