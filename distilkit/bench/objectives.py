"""``distilkit bench dskd | pkt | rgo2d | kd | nst | structural | relation``: each objective's shipped form against the naive
form of its paper's formula (or the authors' code) at realistic 3-D sizes, forward + backward."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.bench.base import Case, register
from distilkit.bench.fixtures import street


def naive_dskd(fs: Tensor, ft: Tensor) -> Tensor:
    """SCPNet eq. 1-2 literally, with the two N x N cosine matrices."""
    a = torch.nn.functional.normalize(fs, dim=1)
    b = torch.nn.functional.normalize(ft, dim=1)
    return ((a @ a.T - b @ b.T) ** 2).mean()


@register("dskd")
def dskd_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import dskd

    cases = []
    big = 20_000 if quick else 1_000_000
    small = 2_000 if quick else 16_000
    for n, with_naive in ((big, False), (small, True)):
        g = torch.Generator(device="cpu").manual_seed(0)
        fs = torch.randn(n, 32, generator=g).to(device).requires_grad_(True)
        ft = torch.randn(n, 32, generator=g).to(device)
        cases.append(Case("dskd", f"{n:,} × 32", lambda fs=fs, ft=ft: dskd(fs, ft),
                          (lambda fs=fs, ft=ft: naive_dskd(fs, ft)) if with_naive else None, [fs],
                          None if with_naive else (lambda fs=fs, ft=ft: dskd(fs.detach().double(), ft.double()))))
    return cases


def naive_pkt(s: Tensor, t: Tensor, eps: float = 1e-7) -> Tensor:
    """RepDistiller's PKT: full N x N kernels."""
    xs = torch.nan_to_num(s / (s.norm(dim=1, keepdim=True) + eps))
    xt = torch.nan_to_num(t / (t.norm(dim=1, keepdim=True) + eps))
    ks, kt = (xs @ xs.T + 1) / 2, (xt @ xt.T + 1) / 2
    ps, pt = ks / ks.sum(1, keepdim=True), kt / kt.sum(1, keepdim=True)
    return (pt * torch.log((pt + eps) / (ps + eps))).mean()


@register("pkt")
def pkt_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import pkt

    n = 2_048 if quick else 16_384
    g = torch.Generator().manual_seed(0)
    fs = torch.randn(n, 32, generator=g).to(device).requires_grad_(True)
    ft = torch.randn(n, 32, generator=g).to(device)
    return [Case("pkt", f"{n:,} sampled voxels × 32", lambda: pkt(fs, ft), lambda: naive_pkt(fs, ft), [fs])]


def _ssc_logits(device: torch.device, quick: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, str]:
    shape = (64, 64, 8) if quick else (256, 256, 32)
    g = torch.Generator().manual_seed(0)
    s = torch.randn(1, 20, *shape, generator=g).to(device).requires_grad_(True)
    t = torch.randn(1, 20, *shape, generator=g).to(device)
    occupied = (torch.rand(1, *shape, generator=g) < 0.10).to(device)
    labels = torch.randint(1, 20, (1, *shape), generator=g).to(device) * (torch.rand(1, *shape, generator=g) < 0.3).to(device)
    return s, t, occupied, labels, f"1 × 20 × {' × '.join(map(str, shape))}"


def naive_rgo2d(s: Tensor, t: Tensor, labels: Tensor, mask: Tensor) -> Tensor:
    """The authors' broadcast form (seed_code.md §2.2): N x K x C masked products, unique classes per region."""
    from distilkit.losses.logit import pearson_rows
    from distilkit.losses.rgo2d import range_regions

    total = s.sum() * 0
    for w, reg in zip((0.06, 0.15, 0.20), range_regions(tuple(s.shape[2:]), "boxes", s.device)):
        m = (mask[0] & reg).reshape(-1)
        ys, yt, lab = s[0].flatten(1).T[m], t[0].flatten(1).T[m], labels[0].reshape(-1)[m]
        u = torch.unique(lab)
        u = u[u != 0]
        if u.numel() == 0:
            continue
        member = (lab[:, None] == u[None, :]).to(ys.dtype)
        gs = (ys[:, None, :] * member[:, :, None]).sum(0) / (member.sum(0)[:, None] + 1e-8)
        gt = (yt[:, None, :] * member[:, :, None]).sum(0) / (member.sum(0)[:, None] + 1e-8)
        ps, pt = gs.softmax(1), gt.softmax(1)
        glob = 2.625 * (1 - pearson_rows(ps, pt).mean()) + 0.375 * (1 - pearson_rows(ps.T, pt.T).mean())
        a_s = torch.nn.functional.cosine_similarity(ys[:, None] + 1e-8, gs[None] + 1e-8, dim=-1)
        a_t = torch.nn.functional.cosine_similarity(yt[:, None] + 1e-8, gt[None] + 1e-8, dim=-1)
        total = total + w * (glob + ((a_s - a_t) ** 2).mean())
    return total


@register("rgo2d")
def rgo2d_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import rgo2d

    s, t, occupied, labels, size = _ssc_logits(device, quick)
    return [Case("rgo2d", size + ", 10 % occupied", lambda: rgo2d(s, t, labels, occupied),
                 lambda: naive_rgo2d(s, t, labels, occupied), [s])]


def naive_kd(s: Tensor, t: Tensor, mask: Tensor) -> Tensor:
    """KD as usually written: softmax maps, elementwise KL, mean over the selected voxels."""
    ps, pt = torch.softmax(s, 1), torch.softmax(t, 1)
    kl = (pt * (torch.log(pt) - torch.log(ps))).sum(1)
    return kl[mask].mean()


@register("kd")
def kd_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import kd

    s, t, occupied, _, size = _ssc_logits(device, quick)
    valid = torch.ones_like(occupied)
    return [Case("kd", size, lambda: kd(s, t, 1.0, valid), lambda: naive_kd(s, t, valid), [s])]


def naive_nst(s: Tensor, t: Tensor) -> Tensor:
    """RepDistiller's NST: broadcast polynomial kernel over (B, C, C, S)."""
    s = torch.nn.functional.normalize(s.flatten(2), dim=2)
    t = torch.nn.functional.normalize(t.flatten(2), dim=2)

    def poly(a: Tensor, b: Tensor) -> Tensor:
        return (a.unsqueeze(1) * b.unsqueeze(2)).sum(-1).pow(2)

    return poly(t, t).mean() + poly(s, s).mean() - 2 * poly(s, t).mean()


@register("nst")
def nst_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses import nst

    cases = []
    sizes = [((32, 32, 4), False), ((16, 16, 4), True)] if quick else [((128, 128, 16), False), ((32, 32, 8), True)]
    for shape, with_naive in sizes:
        g = torch.Generator().manual_seed(0)
        fs = torch.randn(1, 128, *shape, generator=g).to(device).requires_grad_(True)
        ft = torch.randn(1, 128, *shape, generator=g).to(device)
        cases.append(Case("nst", f"1 × 128 × {' × '.join(map(str, shape))}", lambda fs=fs, ft=ft: nst(fs, ft),
                          (lambda fs=fs, ft=ft: naive_nst(fs, ft)) if with_naive else None, [fs]))
    return cases


def released_keypoints(points: Tensor, sample: Tensor, k: int, keep: int) -> Tensor:
    """ScoreLiDAR's released key points: a full distance matrix of the sample, argsort, a Python loop of
    eigen-decompositions (seed_code.md §3.5)."""
    p = points[sample]
    nbr = torch.argsort(torch.cdist(p, p), dim=1)[:, 1:k + 1]
    curv = []
    for i in range(p.shape[0]):
        c = p[nbr[i]] - p[nbr[i]].mean(0)
        lam = torch.linalg.eigvalsh(c.T @ c / k)
        curv.append(lam[0] / lam.sum())
    return sample[torch.topk(torch.stack(curv), keep).indices]


def naive_structural(gen: Tensor, gt: Tensor, key: Tensor) -> Tensor:
    """Eq. 12 and 16 literally: a full generated x ground-truth distance matrix for the nearest points, and
    the key points' distance matrices from (n, n, 3) differences."""
    nn_sq = torch.cdist(gen, gt).min(dim=1).values ** 2
    k = gt[key]
    matched = gen[torch.cdist(k, gen).argmin(dim=1)]
    d_t = (k[:, None] - k[None]).norm(dim=-1)
    d_g = (matched[:, None] - matched[None]).norm(dim=-1)
    return 0.5 * nn_sq.mean() + 0.01 * ((d_t - d_g) ** 2).mean()


@register("structural")
def structural_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.losses.structural import curvature, select_keypoints, structural

    big, small = (18_000, 6_000) if quick else (180_000, 30_000)
    cases = []
    for m, with_naive in ((big, False), (small, True)):
        pts = street(m, 0, device)
        n = round(m * 0.1)
        keep = round(n / 3)

        def fast(pts: Tensor = pts) -> Tensor:
            key = select_keypoints(pts, generator=torch.Generator().manual_seed(0))
            return curvature(pts[key.sort().values], k=min(180, len(key) - 1)).double().sum()

        def naive(pts: Tensor = pts, n: int = n, keep: int = keep) -> Tensor:
            sample = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(0))[:n].to(pts.device)
            key = released_keypoints(pts, sample, 180, keep)
            return curvature(pts[key.sort().values], k=min(180, len(key) - 1)).double().sum()

        cases.append(Case("structural key points", f"{m:,} pts → {n:,} sampled → {keep:,} (k = 180)", fast,
                          naive if with_naive else None, []))
    for m, with_naive in ((big, False), ((6_000 if quick else 18_000), True)):
        gt = street(m, 1, device)
        gen = (gt[torch.randperm(m, generator=torch.Generator().manual_seed(2))] +
               0.05 * torch.randn(m, 3, generator=torch.Generator().manual_seed(3)).to(device)).requires_grad_(True)
        key = select_keypoints(gt, generator=torch.Generator().manual_seed(0))
        cases.append(Case("structural step", f"{m:,} generated vs {m:,} GT, {len(key):,} key pts",
                          lambda gen=gen, gt=gt, key=key: structural(gen, gt, key),
                          (lambda gen=gen, gt=gt, key=key: naive_structural(gen, gt, key)) if with_naive else None,
                          [gen], None if with_naive else
                          (lambda gen=gen, gt=gt, key=key: structural(gen.detach().double(), gt.double(), key))))
    return cases



def naive_relation(fs: Tensor, ft: Tensor) -> Tensor:
    """L2COcc's release: the dense (B, P, P) cosine matrices of each model and their mean L1 distance."""
    a = torch.nn.functional.normalize(fs.flatten(2), dim=1)
    b = torch.nn.functional.normalize(ft.flatten(2), dim=1)
    return torch.nn.functional.l1_loss(a.transpose(1, 2) @ a, b.transpose(1, 2) @ b)


@register("relation")
def relation_cases(device: torch.device, quick: bool) -> list[Case]:
    """L2COcc's relational term at a TPV plane of 128 x 128 positions (P^2 = 2.7e8), 64 channels."""
    from distilkit.losses import l2cocc_relation

    side = 48 if quick else 128
    g = torch.Generator().manual_seed(0)
    fs = torch.randn(1, 64, side, side, generator=g).to(device).requires_grad_(True)
    ft = torch.randn(1, 64, side, side, generator=g).to(device)
    return [Case("l2cocc_relation", f"1 × 64 × {side} × {side} (P = {side * side:,})",
                 lambda: l2cocc_relation(fs, ft), lambda: naive_relation(fs, ft), [fs])]
