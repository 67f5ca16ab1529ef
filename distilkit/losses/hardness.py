"""HASSC's hardness-aware terms (Wang et al., CVPR 2024, "Not All Voxels Are Equal", §3.2–3.3; release
songw-zju/HASSC, ``utils/hvm_header.py`` and ``dense_heads/hassc_voxformer_head.py``).

* :func:`local_geometric_anisotropy` (LGA, the local hardness): per voxel, how many of its 6 face neighbours
  (±x, ±y, ±z) carry another semantic label — 0 inside a region, up to 6 on thin structures. The release loads LGA
  from precomputed files it does not ship (``kitti_lga/…/lgas/*.npy``, values 0…6: its LGA metric's class names are
  '0' … '6'); here it is derived from the labels the stage trains on. Our choices: a neighbour outside the volume or
  with the ignore label does not count, an ignored voxel has LGA 0 (no loss reads it).
* :func:`geometry_weighted_ce`: class-weighted CE per valid voxel times (1 + LGA), the mean over each sample's valid
  voxels (the release's ``loss_ssc``), then over the samples: the release trains one sample per GPU
  (``samples_per_gpu=1``) and DDP averages, so its value at B > 1 is the mean of per-sample values
  (``reduce="pooled"``: the mean over the batch's valid voxels, its code run on a batch).
* :func:`sample_hard_voxels` (global hardness): t·N uniform positions, the coarse prediction read there
  (trilinear), hardness 1 / (p₁ − p₂) of its two largest class probabilities, the ω·N hardest kept and N − ω·N
  uniform ones added. The release differs in two places, offered as options or stated: it ranks the two largest
  *logits* (it sorts the logits per voxel, then interpolates: ``rank="logits"``), and it gathers the kept positions
  from the batch flattened with per-sample indices (every sample gets sample 0's positions when B > 1; here each
  sample its own).
* :func:`hard_voxel_ce`: CE at sampled positions times (α + β·LGA), summed over the valid ones and divided by the
  sum of the class weights of their labels (the release's ``loss_hard_voxel_mining``; its teacher branch indexes the
  class weights by the LGA values instead of the labels — not copied), per sample then the mean over the samples
  (the release's one sample per GPU; ``reduce="pooled"``: the sums over the batch).

Positions are (B, N, 3) in [0, 1)³ along the volume's (X, Y, Z) axes; :func:`voxel_sample` reads a (B, C, X, Y, Z)
volume there as ``grid_sample`` does with ``align_corners=False`` (a position c lies at index c·size − ½), zeros
outside.
"""

from __future__ import annotations

import itertools
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.losses.ce import deterministic_form_needed, weighted_cross_entropy

IGNORE = 255
Reduce = Literal["per_sample", "pooled"]


def local_geometric_anisotropy(labels: Tensor, ignore_index: int = IGNORE) -> Tensor:
    """``(B, *spatial)`` float: the number of face neighbours with another label (see the module docstring)."""
    if labels.dim() < 2:
        raise ValueError(f"local_geometric_anisotropy: labels must be (B, *spatial), got {tuple(labels.shape)}")
    valid = labels != ignore_index
    out = torch.zeros(labels.shape, dtype=torch.float32, device=labels.device)
    for axis in range(1, labels.dim()):
        n = labels.shape[axis]
        if n < 2:
            continue
        a, b = labels.narrow(axis, 0, n - 1), labels.narrow(axis, 1, n - 1)
        differs = ((a != b) & valid.narrow(axis, 0, n - 1) & valid.narrow(axis, 1, n - 1)).float()
        out.narrow(axis, 0, n - 1).add_(differs)
        out.narrow(axis, 1, n - 1).add_(differs)
    return out


def _per_sample_or_pooled(num: Tensor, den: Tensor, reduce: str) -> Tensor:
    """(B,) numerators and denominators: mean_b num_b / den_b (0 where den_b = 0; ``per_sample``) or
    sum num / sum den (``pooled``; 0 where the sum is 0)."""
    if reduce == "pooled":
        num, den = num.sum().reshape(1), den.sum().reshape(1)
    elif reduce != "per_sample":
        raise ValueError(f"reduce must be per_sample or pooled, got {reduce!r}")
    return torch.where(den > 0, num / torch.where(den > 0, den, torch.ones_like(den)), num * 0).mean()


def geometry_weighted_ce(logits: Tensor, labels: Tensor, class_weights: Tensor | None, lga: Tensor,
                         ignore_index: int = IGNORE, reduce: Reduce = "per_sample") -> Tensor:
    """w_y · CE(z, y) · (1 + LGA) on ``(B, K, *S)`` logits, ``(B, *S)`` labels and LGA, averaged over each sample's
    valid voxels then over the samples (``per_sample``: the release, one sample per GPU) or over the batch's valid
    voxels pooled (``pooled``); a sample (batch) without a valid voxel gives 0."""
    if labels.shape != logits.shape[:1] + logits.shape[2:] or lga.shape != labels.shape:
        raise ValueError(f"geometry_weighted_ce: logits {tuple(logits.shape)}, labels {tuple(labels.shape)} and LGA "
                         f"{tuple(lga.shape)} must be (B, K, *S), (B, *S) and (B, *S)")
    valid = labels != ignore_index
    weight = class_weights.to(logits.dtype) if class_weights is not None else None
    ce = weighted_cross_entropy(logits, labels.long().masked_fill(~valid, 0), weight, reduction="none")
    per_voxel = torch.where(valid, ce * (1.0 + lga.to(ce.dtype)), torch.zeros_like(ce)).flatten(1)
    return _per_sample_or_pooled(per_voxel.sum(1), valid.flatten(1).sum(1).to(ce.dtype), reduce)


def voxel_sample(volume: Tensor, coords: Tensor, mode: str = "bilinear", deterministic: bool | None = None) -> Tensor:
    """(B, C, N) values of a (B, C, X, Y, Z) volume at (B, N, 3) positions in [0, 1)³ (``mode``: ``bilinear`` =
    trilinear, or ``nearest``).

    ``deterministic`` (default: off the CPU under deterministic algorithms,
    ``deterministic_form_needed``): the same values read with ``gather`` from the 8 corners
    (``bilinear``) or the nearest voxel, instead of ``F.grid_sample``, whose CUDA backward PyTorch flags
    (``grid_sampler_3d_backward_cuda does not have a deterministic implementation``); ``gather``'s backward is
    deterministic under that setting. The same as ``grid_sample`` up to the rounding of its weights (float64: 1e-15)."""
    if volume.dim() != 5 or coords.dim() != 3 or coords.shape[-1] != 3 or coords.shape[0] != volume.shape[0]:
        raise ValueError(f"voxel_sample: volume {tuple(volume.shape)} must be (B, C, X, Y, Z) and positions "
                         f"{tuple(coords.shape)} (B, N, 3)")
    if mode not in ("bilinear", "nearest"):
        raise ValueError(f"voxel_sample: mode must be 'bilinear' or 'nearest', got {mode!r}")
    if deterministic if deterministic is not None else deterministic_form_needed(volume):
        return _gather_sample(volume, coords, mode)
    grid = (2.0 * coords.flip(-1) - 1.0).to(volume.dtype)[:, :, None, None, :]  # grid_sample's order is (z, y, x)
    return F.grid_sample(volume, grid, mode=mode, align_corners=False)[:, :, :, 0, 0]


def _gather_sample(volume: Tensor, coords: Tensor, mode: str) -> Tensor:
    """:func:`voxel_sample` by ``gather``: a position c lies at index c·size − ½ along each axis; trilinear weights
    over the 8 surrounding voxels, or the nearest one (rounded half to even, as ``grid_sample``); zeros outside.
    Positions, weights and sums in float32 at least (a bfloat16 volume under autocast too), the result in the
    volume's dtype."""
    b, c = volume.shape[:2]
    work = torch.promote_types(volume.dtype, torch.float32)
    sizes = torch.tensor(volume.shape[2:], device=volume.device)
    flat = volume.reshape(b, c, -1)
    at = coords.to(work) * sizes.to(work) - 0.5  # (B, N, 3)

    def read(index: Tensor) -> tuple[Tensor, Tensor]:  # (B, C, N) values at integer (B, N, 3) indices, and inside
        inside = ((index >= 0) & (index < sizes)).all(-1)
        index = torch.minimum(index.clamp_min(0), sizes - 1)
        linear = (index[..., 0] * sizes[1] + index[..., 1]) * sizes[2] + index[..., 2]
        return flat.gather(2, linear[:, None, :].expand(b, c, -1)), inside

    if mode == "nearest":
        values, inside = read(torch.round(at).long())
        return values * inside[:, None, :].to(values.dtype)
    low = at.floor()
    frac = at - low
    low = low.long()
    out = torch.zeros(b, c, coords.shape[1], dtype=work, device=volume.device)
    for step in torch.tensor(list(itertools.product((0, 1), repeat=3)), device=volume.device):
        weight = torch.where(step.bool(), frac, 1.0 - frac).prod(-1)  # (B, N)
        values, inside = read(low + step)
        out = out + values.to(work) * (weight * inside.to(work))[:, None, :]
    return out.to(volume.dtype)


@torch.no_grad()
def sample_hard_voxels(coarse: Tensor, n: int = 4096, oversample: int = 3, omega: float = 0.75,
                       rank: Literal["probabilities", "logits"] = "probabilities") -> Tensor:
    """(B, n, 3) positions: the ⌊ω·n⌋ hardest of ``oversample``·n uniform draws per sample, then n − ⌊ω·n⌋ uniform
    ones (drawn in that order from the default generator of ``coarse``'s device)."""
    if coarse.dim() != 5 or coarse.shape[1] < 2:
        raise ValueError(f"sample_hard_voxels: the coarse prediction must be (B, K >= 2, X, Y, Z), got "
                         f"{tuple(coarse.shape)}")
    if n < 1 or oversample < 1 or not 0.0 <= omega <= 1.0 or int(omega * n) > oversample * n:
        raise ValueError(f"sample_hard_voxels: need n >= 1, oversample >= 1 and 0 <= omega <= 1 (got {n}, "
                         f"{oversample}, {omega})")
    b, hard = coarse.shape[0], int(omega * n)
    draws = torch.rand(b, oversample * n, 3, device=coarse.device)
    if rank == "logits":  # the release: the logits sorted per voxel, then interpolated
        top = voxel_sample(coarse.float().sort(1, descending=True)[0][:, :2], draws)
        p1, p2 = top[:, 0], top[:, 1]
    else:
        top = voxel_sample(coarse.float(), draws).softmax(1).topk(2, dim=1)[0]
        p1, p2 = top[:, 0], top[:, 1]
    hardness = 1.0 / (p1 - p2)
    index = hardness.topk(hard, dim=1)[1]
    kept = draws.gather(1, index[:, :, None].expand(-1, -1, 3))
    uniform = torch.rand(b, n - hard, 3, device=coarse.device)
    return torch.cat([kept, uniform], 1)


def hard_voxel_ce(logits: Tensor, labels: Tensor, lga: Tensor, class_weights: Tensor, alpha: float = 0.2,
                  beta: float = 1.0, ignore_index: int = IGNORE, reduce: Reduce = "per_sample") -> Tensor:
    """Σ_valid CE(z_i, y_i)·(α + β·LGA_i) / Σ_valid w_{y_i} over (B, K, N) logits at sampled positions, their (B, N)
    labels and LGA: per sample, then the mean over the samples (``per_sample``: the release, one sample per GPU), or
    the sums over the batch pooled (``pooled``); 0 for a sample (batch) without a valid position."""
    if labels.shape != logits.shape[:1] + logits.shape[2:] or lga.shape != labels.shape:
        raise ValueError(f"hard_voxel_ce: logits {tuple(logits.shape)}, labels {tuple(labels.shape)} and LGA "
                         f"{tuple(lga.shape)} must be (B, K, N), (B, N) and (B, N)")
    valid = labels != ignore_index
    target = labels.long().masked_fill(~valid, 0)
    ce = weighted_cross_entropy(logits, target, reduction="none")
    num = torch.where(valid, ce * (alpha + beta * lga.to(ce.dtype)), torch.zeros_like(ce)).sum(1)
    den = torch.where(valid, class_weights.to(ce.dtype)[target], torch.zeros_like(ce)).sum(1)
    return _per_sample_or_pooled(num, den, reduce)


__all__ = ["geometry_weighted_ce", "hard_voxel_ce", "local_geometric_anisotropy", "sample_hard_voxels",
           "voxel_sample"]
