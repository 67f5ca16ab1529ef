"""Feature distillation: FitNets (Romero et al. 2015), PKT (Passalis & Tefas, ECCV 2018),
NST (Huang & Wang 2017), in the RepDistiller formulation (kd_frameworks.md §4.3), for 3-D maps."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint


def fitnet(student: Tensor, teacher: Tensor) -> Tensor:
    """Mean squared error between (already regressed) student features and teacher features."""
    if student.shape != teacher.shape:
        raise ValueError(f"fitnet: student {tuple(student.shape)} and teacher {tuple(teacher.shape)} differ "
                         "(the fitnets objective's 1x1 regressor maps the student's channels)")
    if student.numel() == 0:
        return student.sum() * 0.0
    return F.mse_loss(student, teacher.to(student.dtype))


def _pkt_normalise(x: Tensor, eps: float) -> Tensor:
    out = x / (x.norm(dim=1, keepdim=True) + eps)
    return torch.nan_to_num(out, nan=0.0)


def _pkt_block(xs_blk: Tensor, xt_blk: Tensor, xs: Tensor, xt: Tensor, eps: float) -> Tensor:
    ks = (xs_blk @ xs.T + 1.0) / 2.0
    kt = (xt_blk @ xt.T + 1.0) / 2.0
    ps = ks / ks.sum(1, keepdim=True)
    pt = kt / kt.sum(1, keepdim=True)
    return (pt * torch.log((pt + eps) / (ps + eps))).sum()


def _pkt_fused(xs: Tensor, xt: Tensor, eps: float, block: int, grad: bool) -> tuple[Tensor, Tensor | None]:
    """Sum over all N^2 entries of p_t (log(p_t + eps) - log(p_s + eps)) and its gradient with respect
    to the normalised student rows, in one pass over row blocks (no N x N matrix, no recomputation).

    With k = (x x^T + 1)/2, r_i = sum_j k_ij = (N + x_i . sum_j x_j)/2 and k' = k + eps r:
    p + eps = k'/r, so row i contributes (1/rt_i) sum_j kt_ij log(kt'_ij / ks'_ij) - log rt_i + log rs_i
    (one logarithm of a ratio: no cancellation between two large sums). With Q = kt / ks',
    dL/dks_ij = -Q_ij/rt_i - c_i/rs_i, c_i = -1 + eps rs_i sum_j Q_ij / rt_i.
    The (block, N) work buffers are allocated once and reused (no page faults per block).
    """
    n = xs.shape[0]
    sum_s, sum_t = xs.sum(0), xt.sum(0)
    xs_t, xt_t = xs.T.contiguous(), xt.T.contiguous()
    total = torch.zeros((), dtype=torch.float64, device=xs.device)
    g_all = torch.zeros_like(xs) if grad else None
    g_col = torch.zeros_like(xs) if grad else None
    g_shift = xs.new_zeros(xs.shape[1])  # the part of dL/dxs_j shared by all rows j
    half = 0.5
    rows_max = min(block, n)
    ks_buf, kt_buf = xs.new_empty(rows_max, n), xs.new_empty(rows_max, n)
    q_buf = xs.new_empty(rows_max, n) if grad else None

    for start in range(0, n, block):
        stop = min(start + block, n)
        xs_r, xt_r = xs[start:stop], xt[start:stop]
        rs = half * (n + xs_r @ sum_s)  # (b,)
        rt = half * (n + xt_r @ sum_t)
        ks, kt = ks_buf[: stop - start], kt_buf[: stop - start]
        torch.mm(xs_r, xs_t, out=ks).mul_(half).add_((half + eps * rs).unsqueeze(1))  # ks'
        torch.mm(xt_r, xt_t, out=kt).mul_(half).add_(half)  # kt
        ks.reciprocal_()  # 1 / ks'
        if grad:
            assert q_buf is not None
            q = torch.mul(kt, ks, out=q_buf[: stop - start])
            ratio = ks.mul_((eps * rt).unsqueeze(1)).add_(q)  # kt' / ks' = Q + eps rt / ks'
        else:
            ratio = ks.mul_(kt + (eps * rt).unsqueeze(1))
        log_ratio = ratio.log_()
        rows = torch.linalg.vecdot(kt, log_ratio, dim=1) / rt - torch.log(rt) + torch.log(rs)
        total += rows.double().sum()
        if grad:
            assert g_all is not None and g_col is not None
            c = -1.0 + eps * rs * q.sum(1) / rt
            w = (c / rs).unsqueeze(1)  # row constant of dL/dks
            inv_rt = (1.0 / rt).unsqueeze(1)
            # dL/dxs_i (block rows) = 1/2 sum_j gk_ij xs_j; dL/dxs_j (all) += 1/2 sum_i gk_ij xs_i
            g_all[start:stop] += -half * (inv_rt * (q @ xs)) - half * w * sum_s
            g_col.addmm_(q.T, xs_r * inv_rt, alpha=-half)  # in place: no (N, D) temporary per block
            g_shift -= half * (w * xs_r).sum(0)
    if grad:
        assert g_all is not None and g_col is not None
        g_all += g_col + g_shift
    return total, g_all


class _PKT(torch.autograd.Function):
    """PKT with a hand-written backward: the gradient is accumulated in the forward pass."""

    @staticmethod
    def forward(ctx, student: Tensor, xt: Tensor, eps: float, block: int) -> Tensor:  # type: ignore[override]
        norm = student.norm(dim=1, keepdim=True)
        xs = torch.nan_to_num(student / (norm + eps), nan=0.0)
        total, g = _pkt_fused(xs, xt, eps, block, ctx.needs_input_grad[0])
        n2 = float(student.shape[0]) ** 2
        ctx.save_for_backward(student, norm, g if g is not None else student.new_zeros(0))
        ctx.n2, ctx.eps = n2, eps
        return (total / n2).to(student.dtype)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, None, None, None]:  # type: ignore[override]
        x, norm, g = ctx.saved_tensors
        if g.numel() == 0:
            return None, None, None, None
        g = g * (grad / ctx.n2)
        # through xs = x / (||x|| + eps): g / (n + eps) - x <x, g> / (n (n + eps)^2), 0 for the second at n = 0
        inv = 1.0 / (norm + ctx.eps)
        second = torch.where(norm > 0, (x * g).sum(1, keepdim=True) * inv * inv / norm.clamp_min(1e-30),
                             torch.zeros_like(norm))
        return g * inv - x * second, None, None, None


def pkt(student: Tensor, teacher: Tensor, eps: float = 1e-7, block: int = 64) -> Tensor:
    """PKT: cosine kernels rescaled to [0, 1] and row-normalised into conditional probabilities;
    mean over all N^2 entries of p_t * log((p_t + eps) / (p_s + eps)).

    (N, D_s) and (N, D_t) rows (voxels or points; D may differ). Exact, in row blocks with the
    gradient accumulated in the same pass (memory O(block * N), not O(N^2)). N = 1 gives 0.
    A teacher that requires grad takes the autograd path (blocks recomputed in the backward pass).
    """
    if student.dim() != 2 or teacher.dim() != 2 or student.shape[0] != teacher.shape[0]:
        raise ValueError(f"pkt: expects (N, D_s) and (N, D_t) with the same N, got {tuple(student.shape)} and {tuple(teacher.shape)}")
    n = student.shape[0]
    if n == 0:
        return student.sum() * 0.0
    teacher = teacher.to(student.dtype)
    if not (torch.is_grad_enabled() and teacher.requires_grad):
        xt = _pkt_normalise(teacher.detach(), eps)
        return _PKT.apply(student, xt, eps, block)
    xs = _pkt_normalise(student, eps)
    xt = _pkt_normalise(teacher, eps)
    total = student.new_zeros(())
    for start in range(0, n, 2048):
        sl = slice(start, start + 2048)
        total = total + checkpoint(_pkt_block, xs[sl], xt[sl], xs, xt, eps, use_reentrant=False)
    return total / float(n) ** 2


def nst(student: Tensor, teacher: Tensor) -> Tensor:
    """NST: squared MMD with the polynomial kernel k(a, b) = (a^T b)^2 between the sets of
    channel responses, each channel L2-normalised over space.

    ``(B, C_s, *S)`` and ``(B, C_t, *S)`` with equal spatial shape (2-D or 3-D); C_s != C_t allowed.
    L = mean k(T, T) + mean k(S, S) - 2 mean k(S, T), means over B x C x C'. Computed with C x C
    Gram matrices (no C x C x S tensor).
    """
    if student.dim() < 3 or student.shape[0] != teacher.shape[0] or student.shape[2:] != teacher.shape[2:]:
        raise ValueError(f"nst: expects (B, C, *S) maps with the same B and spatial shape, got {tuple(student.shape)} "
                         f"and {tuple(teacher.shape)} (resample the larger map first)")
    s = F.normalize(student.flatten(2), dim=2)
    t = F.normalize(teacher.to(student.dtype).flatten(2), dim=2)
    kss = (s @ s.transpose(1, 2)).pow(2).mean()
    ktt = (t @ t.transpose(1, 2)).pow(2).mean()
    kst = (s @ t.transpose(1, 2)).pow(2).mean()
    return ktt + kss - 2.0 * kst
