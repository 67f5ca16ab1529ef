"""``distilkit bench bev``: issue 60's terms at their papers' sizes, each against the release's own form (its
per-sample loops, boolean indexing and dense matrices, as the tests transcribe them): LiCROcc's PDD (17 classes on
512 x 512 x 40), CMRD (three BEV scales, 128 x 256², 256 x 128², 512 x 64²) and BRD (three maps resized to 32 x 32,
and unresized at 128 x 128: P² = 2.7e8, tiles against the dense matrices), MonoOcc's voxel KL (128 channels on its
128 x 128 x 16 query volume; the release's raw form, and the default softmax form against a per-sample loop) and its
image term (128 channels at 48 x 160, the teacher's 24 x 80 resized), and the voxel-to-BEV term (64 channels, 150,000
active voxels of a 480 x 360 x 32 cylinder grid onto its 480 x 360 plane). ``--quick``: every size about 8x smaller
per axis pair."""

from __future__ import annotations

import warnings

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.bench.base import Case, register


def _release_pdd(s: Tensor, t: Tensor, target: Tensor) -> Tensor:
    """LiCROcc's Distill_1_loss: per sample, the boolean-indexed voxels' KLDivLoss(mean), summed / B."""
    b, c = s.shape[:2]
    log_q = F.log_softmax(s, dim=1).permute(0, 2, 3, 4, 1).reshape(b, -1, c)
    p = F.softmax(t, dim=1).permute(0, 2, 3, 4, 1).reshape(b, -1, c)
    tgt = target.reshape(b, -1)
    total = s.new_zeros(())
    for i in range(b):
        keep = (tgt[i] != 0) & (tgt[i] != 255)
        with warnings.catch_warnings():  # PyTorch's note on "mean": the release's reduction, as it is
            warnings.simplefilter("ignore", UserWarning)
            total = total + F.kl_div(log_q[i][keep], p[i][keep], reduction="mean")
    return total / b


def _release_cmrd(students: list[Tensor], teachers: list[Tensor], masks: list[Tensor]) -> Tensor:
    """LiCROcc's Distill_2: per sample and scale 1 - cos over the masked cells' channels, mean, / (scales x B)."""
    total = students[0].new_zeros(())
    for i in range(students[0].shape[0]):
        for s, t, m in zip(students, teachers, masks):
            total = total + (1 - F.cosine_similarity(s[i][:, m[i]], t[i][:, m[i]], dim=0)).mean()
    return total / (len(students) * students[0].shape[0])


def _release_brd(students: list[Tensor], teachers: list[Tensor], size: tuple[int, int] | None) -> Tensor:
    """LiCROcc's Distill_3: per map, resized, the dense (B, P, P) cosine matrices' L1 mean / B, summed."""
    total = students[0].new_zeros(())
    for s, t in zip(students, teachers):
        if size is not None:
            s, t = F.interpolate(s, size=size, mode="bilinear"), F.interpolate(t, size=size, mode="bilinear")
        gs, gt = F.normalize(s.flatten(2), dim=1), F.normalize(t.flatten(2), dim=1)
        total = total + F.l1_loss(gs.transpose(1, 2) @ gs, gt.transpose(1, 2) @ gt) / s.shape[0]
    return total


def _release_monoocc(s: Tensor, t: Tensor, mask: Tensor) -> Tensor:
    """MonoOcc's Distill_loss at batch 1: [C, N] of the masked voxels, KLDivLoss(mean, log_target) on raw values."""
    with warnings.catch_warnings():  # PyTorch's note on "mean": the release's reduction, as it is
        warnings.simplefilter("ignore", UserWarning)
        return F.kl_div(s.squeeze(0)[:, mask[0]][None], t.squeeze(0)[:, mask[0]][None], reduction="mean",
                        log_target=True)


def _looped_softmax_kl(s: Tensor, t: Tensor, mask: Tensor) -> Tensor:
    """distilkit's default MonoOcc form written as the release writes its own: per sample, [N, C] of the masked
    voxels, KLDivLoss(mean) of the channel softmaxes (log_target), averaged over the batch."""
    total = s.new_zeros(())
    for i in range(s.shape[0]):
        rows_s = F.log_softmax(s[i][:, mask[i]].T, dim=1)
        rows_t = F.log_softmax(t[i][:, mask[i]].T, dim=1)
        with warnings.catch_warnings():  # PyTorch's note on "mean": the release's reduction, as it is
            warnings.simplefilter("ignore", UserWarning)
            total = total + F.kl_div(rows_s, rows_t, reduction="mean", log_target=True)
    return total / s.shape[0]


def _release_image(s: Tensor, t: Tensor) -> Tensor:
    """MonoOcc's cos_similarity_2d without its ratio: the teacher resized (bilinear, corners aligned), the pixels as
    rows, 1 - the mean cosine over the channels."""
    c, (h, w) = s.shape[1], s.shape[2:]
    t = F.interpolate(t, size=(h, w), mode="bilinear", align_corners=True)
    return 1 - F.cosine_similarity(s.permute(0, 2, 3, 1).reshape(-1, c), t.permute(0, 2, 3, 1).reshape(-1, c)).mean()


def _dense_column_max(voxels: object, b: int) -> Tensor:
    """The voxels' column max through a dense (B, C, X, Y, Z) volume filled with -inf (empty columns then 0)."""
    coords, feats = voxels.coords, voxels.feats  # type: ignore[attr-defined]
    x, y, z = voxels.spatial_shape  # type: ignore[attr-defined]
    dense = feats.new_full((b, x, y, z, feats.shape[1]), float("-inf"))
    dense = dense.index_put((coords[:, 0], coords[:, 1], coords[:, 2], coords[:, 3]), feats)
    top = dense.amax(dim=3)
    return torch.where(torch.isinf(top), torch.zeros_like(top), top).permute(0, 3, 1, 2)


@register("bev")
def bev_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import (bev_from_voxels, collapse_height, column_weights, licrocc_affinity, licrocc_bev,
                                  licrocc_kl, monoocc_image, monoocc_kl)
    from distilkit.structures import SparseVoxels

    g = torch.Generator().manual_seed(0)
    cases = []
    grid = (128, 128, 10) if quick else (512, 512, 40)  # nuScenes-Occupancy's, 17 classes
    s = torch.randn(1, 17, *grid, generator=g).to(device).requires_grad_(True)
    t = torch.randn(1, 17, *grid, generator=g).to(device)
    target = torch.randint(0, 17, (1, *grid), generator=g)
    target[torch.rand(target.shape, generator=g) < 0.9] = 0  # most voxels empty
    target = target.to(device)
    cases.append(Case("licrocc_kl (PDD)", f"1 × 17 × {' × '.join(map(str, grid))}",
                      lambda: licrocc_kl(s, t, target), lambda: _release_pdd(s, t, target), [s]))

    div = 4 if quick else 1
    scales = [(128, 256 // div), (256, 128 // div), (512, 64 // div)]
    students = [torch.randn(1, c, n, n, generator=g).to(device).requires_grad_(True) for c, n in scales]
    teachers = [torch.randn(1, c, n, n, generator=g).to(device) for c, n in scales]
    masks = [(torch.rand(1, n, n, generator=g) < 0.3).to(device) for _, n in scales]
    sizes = ", ".join(f"{c} × {n}²" for c, n in scales)
    cases.append(Case("licrocc_bev (CMRD)", sizes, lambda: licrocc_bev(students, teachers, masks),
                      lambda: _release_cmrd(students, teachers, masks), students))
    brd = [(256, 128 // div), (512, 64 // div), (512, 32 // div)]
    maps_s = [torch.randn(1, c, n, n, generator=g).to(device).requires_grad_(True) for c, n in brd]
    maps_t = [torch.randn(1, c, n, n, generator=g).to(device) for c, n in brd]
    side = 32 // div
    cases.append(Case("licrocc_affinity (BRD)", ", ".join(f"{c} × {n}²" for c, n in brd) + f" → {side}²",
                      lambda: licrocc_affinity(maps_s, maps_t, (side, side), release_batch=True),
                      lambda: _release_brd(maps_s, maps_t, (side, side)), maps_s))
    big = 48 if quick else 128
    one_s = [torch.randn(1, 64, big, big, generator=g).to(device).requires_grad_(True)]
    one_t = [torch.randn(1, 64, big, big, generator=g).to(device)]
    cases.append(Case("licrocc_affinity unresized", f"1 × 64 × {big}² (P² = {(big * big) ** 2:.1e})",
                      lambda: licrocc_affinity(one_s, one_t, None), lambda: _release_brd(one_s, one_t, None), one_s))

    vol = (32, 32, 4) if quick else (128, 128, 16)  # MonoOcc's query volume
    vs = torch.randn(1, 128, *vol, generator=g).to(device).requires_grad_(True)
    vt = torch.randn(1, 128, *vol, generator=g).to(device)
    vmask = (torch.rand(1, *vol, generator=g) < 0.25).to(device)
    cases.append(Case("monoocc_kl (raw, as released)", f"1 × 128 × {' × '.join(map(str, vol))}",
                      lambda: monoocc_kl(vs, vt, vmask, "raw"), lambda: _release_monoocc(vs, vt, vmask), [vs]))
    cases.append(Case("monoocc_kl (softmax, default)", f"1 × 128 × {' × '.join(map(str, vol))}",
                      lambda: monoocc_kl(vs, vt, vmask, "softmax"), lambda: _looped_softmax_kl(vs, vt, vmask), [vs]))
    img_s, img_t = ((12, 40), (6, 20)) if quick else ((48, 160), (24, 80))  # stride-8 and -16 maps of a KITTI image
    fs = torch.randn(1, 128, *img_s, generator=g).to(device).requires_grad_(True)
    ft = torch.randn(1, 128, *img_t, generator=g).to(device)
    cases.append(Case("monoocc_image", f"1 × 128 × {img_s[0]} × {img_s[1]} (teacher {img_t[0]} × {img_t[1]}, resized)",
                      lambda: monoocc_image(fs, ft), lambda: _release_image(fs, ft), [fs]))

    cyl = (120, 90, 8) if quick else (480, 360, 32)  # the voxel-to-BEV release's cylinder grid
    n = 9_000 if quick else 150_000
    cells = torch.randperm(cyl[0] * cyl[1] * cyl[2], generator=g)[:n]
    coords = torch.stack([torch.zeros_like(cells), cells // (cyl[1] * cyl[2]), cells // cyl[2] % cyl[1],
                          cells % cyl[2]], 1).to(device)
    feats = torch.randn(n, 64, generator=g).to(device).requires_grad_(True)
    voxels = SparseVoxels(coords, feats, cyl)
    student = torch.randn(1, 64, cyl[0], cyl[1], generator=g).to(device).requires_grad_(True)
    labels = torch.randint(0, 20, (1, *cyl), generator=g).to(device)
    alpha = (1 / (torch.rand(20, generator=g) / 20 + 0.001) / 50).to(device)
    weights = column_weights(labels, alpha)
    cases.append(Case("bev_from_voxels (LWD)", f"{n:,} voxels × 64 on {' × '.join(map(str, cyl))} → {cyl[0]} × {cyl[1]}",
                      lambda: bev_from_voxels(student, collapse_height(voxels, "max", batch=1), weights),
                      lambda: bev_from_voxels(student, _dense_column_max(voxels, 1), weights), [student, feats]))
    return cases
