"""RGO²D: range-guided offline-to-online distillation (Scribble2Scene, Wang et al. IJCAI 2024, eq. 2-4).

Follows the authors' code (seed_code.md §2.2): inside a region, for each sample, the voxels of the
dense-geometry occupancy ``mask`` are selected; for every scribble class present among them
(label != 0, and != ``ignore_index``, the class table's ignore label) the class-mean logits form the global semantic
logits (GSL, K_c x K). *Global*: DIST-style inter/intra Pearson terms on softmax(GSL) of student
and teacher. *Local* (LSA): each voxel's cosine similarity to every GSL row, student vs teacher,
compared with MSE. Both are averaged over the batch. GSL by ``index_add`` and LSA by a normalised
matmul: O(N K C), no N x N matrix. A region with no labelled class or no occupied voxel gives 0.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.losses.logit import pearson_rows

_EPS = 1e-8


def _gsl(y: Tensor, inv: Tensor, k: int) -> Tensor:
    counts = torch.zeros(k, dtype=y.dtype, device=y.device).index_add_(0, inv, torch.ones_like(inv, dtype=y.dtype))
    sums = torch.zeros(k, y.shape[1], dtype=y.dtype, device=y.device).index_add_(0, inv, y)
    return sums / (counts[:, None] + _EPS)


def centre_affinity(y: Tensor, centres: Tensor) -> Tensor:
    """(N, K_c) cosine similarity of each voxel's logits to each class centre (normalised matmul)."""
    return F.normalize(y, dim=1, eps=_EPS) @ F.normalize(centres, dim=1, eps=_EPS).T


def _check(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, mask: Tensor) -> None:
    if student_logits.shape != teacher_logits.shape or student_logits.dim() < 3:
        raise ValueError(f"rgo2d: expects equal (B, K, *S) logits, got {tuple(student_logits.shape)} and {tuple(teacher_logits.shape)}")
    expect = student_logits.shape[:1] + student_logits.shape[2:]
    if labels.shape != expect or mask.shape != expect:
        raise ValueError(f"rgo2d: labels {tuple(labels.shape)} and mask {tuple(mask.shape)} must be {tuple(expect)}")


def _gather(logits: Tensor, idx: Tensor) -> Tensor:
    """(M, K) rows of one sample's (K, *S) logits at flat voxel indices ``idx``: one gather, whose
    backward is one scatter into the full grid (not one per region)."""
    return logits.reshape(logits.shape[0], -1).index_select(1, idx).T


def _terms(ys: Tensor, yt: Tensor, lab: Tensor, inter: float, intra: float, ignore_index: int) -> tuple[Tensor, Tensor] | None:
    """(global, local) terms of one sample's region from its occupied voxels' rows (M, K) and labels (M,)."""
    k = ys.shape[1]  # labels outside 1..K-1 (unlabelled 254, ignore 255) select nothing
    sel = (lab > 0) & (lab < k) & (lab != ignore_index)
    if not bool(sel.any()):
        return None
    classes, inv = torch.unique(lab[sel], return_inverse=True)
    kc = classes.numel()
    gs = _gsl(ys[sel], inv, kc)
    gt = _gsl(yt[sel], inv, kc)
    ps, pt = gs.softmax(1), gt.softmax(1)
    glob = inter * (1 - pearson_rows(ps, pt).mean()) + intra * (1 - pearson_rows(ps.T, pt.T).mean())
    # LSA over every occupied voxel of the region (labelled or not), as in the code
    return glob, F.mse_loss(centre_affinity(ys, gs), centre_affinity(yt, gt))


def rgo2d_region(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, mask: Tensor,
                 inter: float = 2.625, intra: float = 0.375, ignore_index: int = 255) -> tuple[Tensor, Tensor]:
    """(global, local) RGO²D terms of one region.

    Args:
        student_logits, teacher_logits: ``(B, K, *S)`` logits (temperature 1, as in the code).
        labels: ``(B, *S)`` long scribble labels; only 1..K-1 are classes (0 empty, 254 unlabelled, 255 ignore).
        mask: ``(B, *S)`` bool, the voxels of this region that are occupied in the dense geometry.
    """
    _check(student_logits, teacher_logits, labels, mask)
    zero = student_logits.sum() * 0.0
    g_total, l_total = zero, zero
    b = student_logits.shape[0]
    for i in range(b):
        idx = mask[i].reshape(-1).nonzero().squeeze(1)
        out = _terms(_gather(student_logits[i], idx), _gather(teacher_logits[i].to(student_logits.dtype), idx),
                     labels[i].reshape(-1)[idx], inter, intra, ignore_index)
        if out is not None:
            g_total, l_total = g_total + out[0], l_total + out[1]
    return g_total / b, l_total / b


def range_regions(shape: Sequence[int], kind: str = "boxes", device: torch.device | None = None) -> list[Tensor]:
    """Region masks (X, Y, Z) bool on an SSC grid (x forward from the sensor at x = 0, y centred).

    ``boxes`` (the code): x < X/4 & |y| < Y/8; x < X/2 & |y| < Y/4; the whole volume (nested; on the
    SemanticKITTI grid 12.8 m / 6.4 m, 25.6 m / 12.8 m, 51.2 m). ``rings``: disjoint radial rings
    r < X/4, X/4 <= r < X/2, r >= X/2 around the sensor.
    """
    x, y, z = shape
    xi = torch.arange(x, device=device).view(-1, 1, 1).float() + 0.5
    yi = torch.arange(y, device=device).view(1, -1, 1).float() + 0.5 - y / 2
    full = torch.ones(x, y, z, dtype=torch.bool, device=device)
    if kind == "boxes":
        return [((xi < x / 4) & (yi.abs() < y / 8)) & full, ((xi < x / 2) & (yi.abs() < y / 4)) & full, full]
    if kind == "rings":
        r = (xi**2 + yi**2).sqrt().expand(x, y, z)
        return [r < x / 4, (r >= x / 4) & (r < x / 2), r >= x / 2]
    raise ValueError(f"rgo2d: regions must be 'boxes', 'rings' or a list of masks, got {kind!r}")


def rgo2d(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, mask: Tensor,
          regions: str | Sequence[Tensor] = "boxes", region_weights: Sequence[float] = (0.06, 0.15, 0.20),
          inter: float = 2.625, intra: float = 0.375, ignore_index: int = 255, local: float = 1.0) -> Tensor:
    """Scribble2Scene eq. 2-4 without the image-feature term: ``sum_r w_r (global_r + local * local_r)`` (``local`` = 1
    in the paper; 0 gives Table 6's global-only ablation, ``inter = intra = 0`` the local-only one).

    ``regions``: ``"boxes"`` (default, the authors' nested boxes), ``"rings"``, or a list of bool
    masks of shape ``(*S)`` or ``(B, *S)``, one per weight. The occupied voxels of all regions are gathered
    once per sample (so the backward pass scatters once into the grid); each region then works on
    its subset of those rows. Equal to ``sum_r w_r * sum(rgo2d_region(..., mask & region_r))``. Labels equal to
    ``ignore_index`` (the class table's) select no class.
    """
    _check(student_logits, teacher_logits, labels, mask)
    spatial = tuple(student_logits.shape[2:])
    masks = range_regions(spatial, regions, student_logits.device) if isinstance(regions, str) else list(regions)
    if len(masks) != len(region_weights):
        raise ValueError(f"rgo2d: {len(masks)} regions but {len(region_weights)} region weights")
    b = student_logits.shape[0]
    regs = []
    for reg in masks:
        reg = reg.to(student_logits.device).bool()
        regs.append(reg.unsqueeze(0).expand(b, *spatial) if reg.shape == spatial else reg)
    total = student_logits.sum() * 0.0
    for i in range(b):
        member = torch.stack([r[i].reshape(-1) for r in regs])  # (R, V)
        idx = (mask[i].reshape(-1).bool() & member.any(0)).nonzero().squeeze(1)
        ys = _gather(student_logits[i], idx)
        yt = _gather(teacher_logits[i].to(student_logits.dtype), idx)
        lab = labels[i].reshape(-1)[idx]
        rows = member[:, idx]
        for w, inside in zip(region_weights, rows):
            out = _terms(ys[inside], yt[inside], lab[inside], inter, intra, ignore_index)
            if out is not None:
                total = total + w * (out[0] + local * out[1]) / b
    return total
