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


def pkt(student: Tensor, teacher: Tensor, eps: float = 1e-7, block: int = 2048) -> Tensor:
    """PKT: cosine kernels rescaled to [0, 1] and row-normalised into conditional probabilities;
    mean over all N^2 entries of p_t * log((p_t + eps) / (p_s + eps)).

    (N, D_s) and (N, D_t) rows (voxels or points; D may differ). Exact, computed in row blocks with
    recomputation in the backward pass, so memory is O(block * N), not O(N^2). N = 1 gives 0.
    """
    if student.dim() != 2 or teacher.dim() != 2 or student.shape[0] != teacher.shape[0]:
        raise ValueError(f"pkt: expects (N, D_s) and (N, D_t) with the same N, got {tuple(student.shape)} and {tuple(teacher.shape)}")
    n = student.shape[0]
    if n == 0:
        return student.sum() * 0.0
    xs = _pkt_normalise(student, eps)
    xt = _pkt_normalise(teacher.to(student.dtype), eps)
    total = student.new_zeros(())
    for start in range(0, n, block):
        sl = slice(start, start + block)
        if torch.is_grad_enabled() and (xs.requires_grad or xt.requires_grad):
            total = total + checkpoint(_pkt_block, xs[sl], xt[sl], xs, xt, eps, use_reentrant=False)
        else:
            total = total + _pkt_block(xs[sl], xt[sl], xs, xt, eps)
    return total / float(n) ** 2


def nst(student: Tensor, teacher: Tensor) -> Tensor:
    """NST: squared MMD with the polynomial kernel k(a, b) = (a^T b)^2 between the sets of
    channel responses, each channel L2-normalised over space.

    (B, C_s, *S) and (B, C_t, *S) with equal spatial shape (2-D or 3-D); C_s != C_t allowed.
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
