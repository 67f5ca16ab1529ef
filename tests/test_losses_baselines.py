"""KD, FitNets, PKT, NST, DIST and RGO²D against independent naive float64 implementations (KD, DIST, PKT and NST on the
device of ``--device``, their references on the CPU)."""

from __future__ import annotations

import copy


import pytest
import torch

import distilkit.losses as L
from conftest import on_device_matches
from distilkit.losses.rgo2d import range_regions

D = torch.float64


def close(a: torch.Tensor, b: torch.Tensor, rel: float = 1e-6) -> bool:
    return bool((a - b).abs() <= rel * b.abs() + 1e-12)


def grads_close(fa, fb, inputs, rel: float = 1e-6) -> None:
    ga = torch.autograd.grad(fa(), inputs, allow_unused=True)
    gb = torch.autograd.grad(fb(), inputs, allow_unused=True)
    for x, y in zip(ga, gb):
        x = torch.zeros(()) if x is None else x
        y = torch.zeros(()) if y is None else y
        assert (x - y).norm() <= rel * y.norm() + 1e-12


# ---- naive references, written from the papers' formulas -------------------------------------
def naive_kd(s, t, T, mask):
    k = s.shape[1]
    rows_s = [s[(b, slice(None)) + idx] for b in range(s.shape[0]) for idx in _spatial(s)
              if mask is None or mask[(b,) + idx]]
    rows_t = [t[(b, slice(None)) + idx] for b in range(s.shape[0]) for idx in _spatial(s)
              if mask is None or mask[(b,) + idx]]
    total = 0.0
    for rs, rt in zip(rows_s, rows_t):
        zs = sum(torch.exp(rs[c] / T) for c in range(k))
        zt = sum(torch.exp(rt[c] / T) for c in range(k))
        for c in range(k):
            pt, ps = torch.exp(rt[c] / T) / zt, torch.exp(rs[c] / T) / zs
            total = total + pt * torch.log(pt / ps)
    return T * T * total / max(len(rows_s), 1)


def _spatial(x):
    import itertools

    return list(itertools.product(*[range(n) for n in x.shape[2:]]))


def naive_pearson(a, b):
    am, bm = a.mean(), b.mean()
    num = sum((a[i] - am) * (b[i] - bm) for i in range(len(a)))
    sa = sum((a[i] - am) ** 2 for i in range(len(a)))
    sb = sum((b[i] - bm) ** 2 for i in range(len(b)))
    na = torch.sqrt(sa) if sa > 0 else sa * 0  # a constant vector (e.g. one row): correlation 0
    nb = torch.sqrt(sb) if sb > 0 else sb * 0
    return num / (na * nb + 1e-8)


def naive_dist(s, t, beta, gamma, T):
    ps, pt = torch.softmax(s / T, 1), torch.softmax(t / T, 1)
    n, k = ps.shape
    inter = 1 - sum(naive_pearson(ps[i], pt[i]) for i in range(n)) / n
    intra = 1 - sum(naive_pearson(ps[:, j], pt[:, j]) for j in range(k)) / k
    return T * T * (beta * inter + gamma * intra)


def naive_pkt(s, t, eps=1e-7):
    def probs(x):
        n = x.shape[0]
        xn = [x[i] / (torch.sqrt((x[i] ** 2).sum()) + eps) for i in range(n)]
        k = [[(xn[i] @ xn[j] + 1) / 2 for j in range(n)] for i in range(n)]
        return [[k[i][j] / sum(k[i]) for j in range(n)] for i in range(n)]

    ps, pt = probs(s), probs(t)
    n = s.shape[0]
    return sum(pt[i][j] * torch.log((pt[i][j] + eps) / (ps[i][j] + eps)) for i in range(n) for j in range(n)) / n**2


def naive_nst(s, t):
    b = s.shape[0]
    S = s.reshape(b, s.shape[1], -1)
    T = t.reshape(b, t.shape[1], -1)
    S = S / S.norm(dim=2, keepdim=True)
    T = T / T.norm(dim=2, keepdim=True)

    def mk(a, c):
        vals = [(a[i, p] @ c[i, q]) ** 2 for i in range(b) for p in range(a.shape[1]) for q in range(c.shape[1])]
        return sum(vals) / len(vals)

    return mk(T, T) + mk(S, S) - 2 * mk(S, T)


def naive_centres(ys, yt, labels, i, vox, classes):
    """Sample i's class centres: the mean student and teacher logits of the voxels ``vox`` of each class."""
    gs, gt = [], []
    for c in classes:
        mem = [idx for idx in vox if int(labels[(i,) + idx]) == c]
        gs.append(sum(ys[(i, slice(None)) + idx] for idx in mem) / len(mem))
        gt.append(sum(yt[(i, slice(None)) + idx] for idx in mem) / len(mem))
    return gs, gt


def naive_rgo2d_region(ys, yt, labels, mask, inter=2.625, intra=0.375):
    b = ys.shape[0]
    g_tot, l_tot = 0.0, 0.0
    for i in range(b):
        vox = [idx for idx in _spatial(ys) if mask[(i,) + idx]]
        classes = sorted({int(labels[(i,) + idx]) for idx in vox} - {0, 255})
        if not classes:
            continue
        gs, gt = naive_centres(ys, yt, labels, i, vox, classes)
        gs, gt = torch.stack(gs), torch.stack(gt)
        ps, pt = gs.softmax(1), gt.softmax(1)
        kc = len(classes)
        g_tot = g_tot + inter * (1 - sum(naive_pearson(ps[j], pt[j]) for j in range(kc)) / kc) \
            + intra * (1 - sum(naive_pearson(ps[:, c], pt[:, c]) for c in range(ps.shape[1])) / ps.shape[1])
        sq = []
        for idx in vox:
            vs, vt = ys[(i, slice(None)) + idx], yt[(i, slice(None)) + idx]
            for j in range(kc):
                cs = vs @ gs[j] / (vs.norm() * gs[j].norm())
                ct = vt @ gt[j] / (vt.norm() * gt[j].norm())
                sq.append((cs - ct) ** 2)
        l_tot = l_tot + sum(sq) / len(sq)
    return g_tot / b, l_tot / b


# ---- tests ----------------------------------------------------------------------------------
@pytest.fixture
def g() -> torch.Generator:
    return torch.Generator().manual_seed(0)


@pytest.mark.parametrize("T", [1.0, 4.0])
@pytest.mark.parametrize("masked", [False, True])
def test_kd(g, T, masked, device) -> None:
    s = torch.randn(2, 4, 3, 2, 2, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(2, 4, 3, 2, 2, dtype=D, generator=g, requires_grad=True)
    mask = (torch.rand(2, 3, 2, 2, generator=g) < 0.5) if masked else None
    on_device_matches(lambda s, t, m: L.kd(s, t, T, m), lambda s, t, m: naive_kd(s, t, T, m), (s, t, mask), device)


def test_kd_empty_mask_and_errors(g) -> None:
    s = torch.randn(1, 3, 2, 2, requires_grad=True)
    assert L.kd(s, s.detach(), mask=torch.zeros(1, 2, 2, dtype=torch.bool)).item() == 0.0
    with pytest.raises(ValueError, match="mask must have shape"):
        L.kd(s, s, mask=torch.ones(2, 2, dtype=torch.bool))


@pytest.mark.parametrize("n", [1, 6])
def test_dist(g, n, device) -> None:
    s = torch.randn(n, 5, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(n, 5, dtype=D, generator=g, requires_grad=True)
    on_device_matches(lambda s, t: L.dist(s, t, 1.5, 0.7, 2.0), lambda s, t: naive_dist(s, t, 1.5, 0.7, 2.0), (s, t),
                      device)


@pytest.mark.parametrize("n,ds,dt", [(1, 3, 3), (9, 4, 6)])
def test_pkt(g, n, ds, dt, device) -> None:
    s = torch.randn(n, ds, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(n, dt, dtype=D, generator=g, requires_grad=True)
    on_device_matches(L.pkt, naive_pkt, (s, t), device)
    # blocked evaluation (with recomputation) equals the one-block value and gradient
    grads_close(lambda: L.pkt(s, t, block=2), lambda: L.pkt(s, t, block=1000), (s, t), rel=1e-10)


@pytest.mark.parametrize("b,cs,ct,spatial", [(1, 3, 3, (4, 3)), (2, 3, 5, (3, 2, 2))])
def test_nst(g, b, cs, ct, spatial, device) -> None:
    s = torch.randn(b, cs, *spatial, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(b, ct, *spatial, dtype=D, generator=g, requires_grad=True)
    on_device_matches(L.nst, naive_nst, (s, t), device)
    with pytest.raises(ValueError, match="spatial shape"):
        L.nst(s, t[..., :1])


def test_fitnet(g, device) -> None:
    s = torch.randn(2, 3, 4, 4, 2, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(2, 3, 4, 4, 2, dtype=D, generator=g)
    on_device_matches(L.fitnet, lambda s, t: sum((a - b) ** 2 for a, b in zip(s.reshape(-1), t.reshape(-1))) / s.numel(),
                      (s, t), device)
    want = sum(float((a - b).detach() ** 2) for a, b in zip(s.reshape(-1), t.reshape(-1))) / s.numel()
    assert L.fitnet(s, t).item() == pytest.approx(want, rel=1e-12)
    (grad,) = torch.autograd.grad(L.fitnet(s, t), s)
    assert torch.allclose(grad, 2 * (s - t) / s.numel())


def _rgo_inputs(g, b=2, k=4, shape=(4, 3, 2)):
    s = torch.randn(b, k, *shape, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(b, k, *shape, dtype=D, generator=g, requires_grad=True)
    labels = torch.randint(0, 4, (b, *shape), generator=g)
    labels[0, 0, 0, 0] = 255
    mask = torch.rand(b, *shape, generator=g) < 0.7
    return s, t, labels, mask


def test_rgo2d_region(g, device) -> None:
    s, t, labels, mask = _rgo_inputs(g)
    on_device_matches(lambda *a: sum(L.rgo2d_region(*a)), lambda *a: sum(naive_rgo2d_region(*a)), (s, t, labels, mask),
                      device)
    fast = L.rgo2d_region(s, t, labels, mask)
    slow = naive_rgo2d_region(s, t, labels, mask)
    assert close(fast[0], slow[0]) and close(fast[1], slow[1])
    grads_close(lambda: sum(L.rgo2d_region(s, t, labels, mask)), lambda: sum(naive_rgo2d_region(s, t, labels, mask)), (s, t))


def test_rgo2d_regions_and_weights(g, device) -> None:
    s, t, labels, mask = _rgo_inputs(g, shape=(8, 8, 2))
    regs = range_regions((8, 8, 2), "boxes")
    on_device_matches(L.rgo2d, lambda s, t, labels, mask: sum(
        w * sum(naive_rgo2d_region(s, t, labels, mask & r)) for w, r in zip((0.06, 0.15, 0.20), regs)),
        (s, t, labels, mask), device)
    assert regs[0].sum() == 2 * 2 * 2 and regs[1].sum() == 4 * 4 * 2 and regs[2].all()
    # the naive regions once (the slow part), their weighted sum's value and gradient against the fast form's
    parts = [naive_rgo2d_region(s, t, labels, mask & r) for r in regs]
    want = sum(w * sum(p) for w, p in zip((0.06, 0.15, 0.20), parts))
    assert close(L.rgo2d(s, t, labels, mask), want)
    grads_close(lambda: L.rgo2d(s, t, labels, mask), lambda: want, (s, t))
    rings = range_regions((8, 8, 2), "rings")
    assert not (rings[0] & rings[1]).any() and (rings[0] | rings[1] | rings[2]).all()
    # Table 6's ablations: the local term weighted (0: global only), or the global one off (inter = intra = 0)
    glob = sum(w * p[0].detach() for w, p in zip((0.06, 0.15, 0.20), parts))
    loc = sum(w * p[1].detach() for w, p in zip((0.06, 0.15, 0.20), parts))
    assert close(L.rgo2d(s, t, labels, mask, local=0.0), glob) and close(L.rgo2d(s, t, labels, mask, local=0.5),
                                                                         glob + 0.5 * loc)
    assert close(L.rgo2d(s, t, labels, mask, inter=0.0, intra=0.0), loc)


def test_rgo2d_empty_regions_are_zero_not_nan(g) -> None:
    s, t, labels, mask = _rgo_inputs(g)
    zero_g, zero_l = L.rgo2d_region(s, t, torch.zeros_like(labels), mask)
    assert zero_g.item() == 0.0 and zero_l.item() == 0.0
    out = L.rgo2d(s, t, labels, torch.zeros_like(mask))
    assert out.item() == 0.0 and out.requires_grad
    # one class only: intra term is the constant 1 (no NaN)
    g1, _ = L.rgo2d_region(s, t, torch.where(labels > 0, 1, 0), mask)
    assert torch.isfinite(g1)


def _double_grid(x: torch.Tensor, first_spatial: int) -> torch.Tensor:
    for d in range(first_spatial, x.dim()):
        x = x.repeat_interleave(2, dim=d)
    return x


def test_scale_free_when_the_grid_doubles(g) -> None:
    s, t, labels, mask = _rgo_inputs(g, shape=(8, 8, 2))
    s2, t2 = _double_grid(s.detach(), 2), _double_grid(t.detach(), 2)
    l2, m2 = _double_grid(labels, 1), _double_grid(mask, 1)
    assert close(L.kd(s2, t2, 2.0, m2), L.kd(s, t, 2.0, mask), 1e-9)
    flat = lambda x: x.movedim(1, -1).reshape(-1, x.shape[1])  # noqa: E731
    assert close(L.dist(flat(s2), flat(t2)), L.dist(flat(s), flat(t)), 1e-9)
    assert close(L.rgo2d(s2, t2, l2, m2), L.rgo2d(s, t, labels, mask), 1e-9)


@pytest.mark.parametrize("n,ds,dt,block", [(1, 3, 3, 4), (9, 4, 6, 2), (13, 5, 5, 4), (7, 3, 2, 100)])
def test_pkt_fused_backward_matches_naive(g, n, ds, dt, block) -> None:
    """A detached teacher (what objectives pass) takes the one-pass path with the hand-written gradient."""
    s = torch.randn(n, ds, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(n, dt, dtype=D, generator=g)
    assert close(L.pkt(s, t, block=block), naive_pkt(s, t))
    if n > 2:  # a zero row normalises to zero, as in the naive form (whose gradient there is undefined)
        z = s.detach().clone()
        z[1] = 0.0
        assert close(L.pkt(z, t, block=block), naive_pkt(z, t))
    grads_close(lambda: L.pkt(s, t, block=block), lambda: naive_pkt(s, t), (s,))
    assert torch.autograd.gradcheck(lambda x: L.pkt(x, t, block=block), (s.detach().clone().add_(0.1).requires_grad_(),))


# ---- CleanerS, PVKD, MGD as plain functions -------------------------------------------------------------------
def naive_cleaners(ys, yt, labels, T, kd_sc, kd_sa, ignore):
    """CleanerS from its definition, voxel by voxel: centres = class means of the labelled voxels, KL of the
    softened centres, MSE of every non-ignored voxel's cosine to every centre."""
    sc_tot, sa_tot, n = 0.0, 0.0, 0
    for i in range(ys.shape[0]):
        vox = [idx for idx in _spatial(ys) if int(labels[(i,) + idx]) != ignore]
        classes = sorted({int(labels[(i,) + idx]) for idx in vox} - {0})
        if not classes:
            continue
        gs, gt = naive_centres(ys, yt, labels, i, vox, classes)
        kl = 0.0
        for a, b in zip(gs, gt):
            ps, pt = torch.softmax(a / T, 0), torch.softmax(b / T, 0)
            kl = kl + sum(pt[k] * torch.log(pt[k] / ps[k]) for k in range(len(pt)))
        sc_tot = sc_tot + T * T * kl / len(classes)
        sq = []
        for idx in vox:
            vs, vt = ys[(i, slice(None)) + idx], yt[(i, slice(None)) + idx]
            for a, b in zip(gs, gt):
                sq.append((vs @ a / (vs.norm() * a.norm()) - vt @ b / (vt.norm() * b.norm())) ** 2)
        sa_tot = sa_tot + sum(sq) / len(sq)
        n += 1
    return (kd_sc * sc_tot + kd_sa * sa_tot) / max(n, 1)


@pytest.mark.parametrize("T", [1.0, 2.0])
def test_cleaners_matches_its_definition(g, T, device) -> None:
    s, t, labels, _ = _rgo_inputs(g)
    labels[1, 1, 1, 0] = 7  # a class id the data may use as its ignore label
    on_device_matches(lambda s, t, labels: L.cleaners(s, t, labels, T, 0.7, 1.3, 7),
                      lambda s, t, labels: naive_cleaners(s, t, labels, T, 0.7, 1.3, 7), (s, t, labels), device)
    fast = L.cleaners(s, t, labels, T, kd_sc=0.7, kd_sa=1.3, ignore_index=7)
    slow = naive_cleaners(s, t, labels, T, 0.7, 1.3, 7)
    assert close(fast, slow)
    grads_close(lambda: L.cleaners(s, t, labels, T, 0.7, 1.3, 7), lambda: naive_cleaners(s, t, labels, T, 0.7, 1.3, 7),
                (s, t))
    assert not close(fast, L.cleaners(s, t, labels, T, 0.7, 1.3, 255))  # the ignore label matters
    fs, ft = torch.randn(2, 3, 4, 4, dtype=D, generator=g), torch.randn(2, 3, 4, 4, dtype=D, generator=g)
    with_features = L.cleaners(s, t, labels, T, 0.7, 1.3, 7, fs, ft, kd_t=0.5)
    assert close(with_features, slow + 0.5 * ((fs - ft) ** 2).mean())
    with pytest.raises(ValueError, match="labels"):
        L.cleaners(s, t, labels[:, :1], T)


def naive_relation_gap(a, b):
    n = a.shape[0]
    return sum((a[i] @ a[j] / (a[i].norm() * a[j].norm()) - b[i] @ b[j] / (b[i].norm() * b[j].norm())) ** 2
               for i in range(n) for j in range(n)) / n**2


def test_pvkd_is_kd_plus_the_mean_relation_gap_inside_supervoxels(g, device) -> None:
    coords = torch.unique(torch.stack([torch.randint(0, 2, (60,), generator=g), torch.randint(0, 8, (60,), generator=g),
                                       torch.randint(0, 8, (60,), generator=g), torch.randint(0, 2, (60,), generator=g)],
                                      1), dim=0)
    fs = torch.randn(len(coords), 3, dtype=D, generator=g, requires_grad=True)
    ft = torch.randn(len(coords), 5, dtype=D, generator=g)
    groups, r_bin = L.supervoxel_ids(coords, (8, 8, 2), radial_bins=2, angular_bins=2, height_bins=1)
    assert int(r_bin.max()) <= 1 and len(torch.unique(groups)) > 2
    # samples never share a supervoxel
    assert not set(groups[coords[:, 0] == 0].tolist()) & set(groups[coords[:, 0] == 1].tolist())
    ls = torch.randn(2, 4, 8, 8, 2, dtype=D, generator=g, requires_grad=True)
    lt = torch.randn(2, 4, 8, 8, 2, dtype=D, generator=g)
    mask = torch.rand(2, 8, 8, 2, generator=g) < 0.5

    def slow():
        gaps = [naive_relation_gap(fs[groups == i], ft[groups == i]) for i in torch.unique(groups)]
        return 0.5 * naive_kd(ls, lt, 2.0, mask) + 10.0 * sum(gaps) / len(gaps)

    def fast():
        return L.pvkd(fs, ft, groups, ls, lt, 2.0, mask, output_weight=0.5, affinity_weight=10.0)

    assert close(fast(), slow())
    grads_close(fast, slow, (fs, ls))
    on_device_matches(lambda fs, ft, groups, ls, lt, mask: L.pvkd(fs, ft, groups, ls, lt, 2.0, mask, output_weight=0.5,
                                                                  affinity_weight=10.0),
                      lambda *a: slow(), (fs, ft, groups, ls, lt, mask), device)
    chosen = torch.tensor([0, 2])
    ids = torch.unique(groups)
    want = sum(naive_relation_gap(fs[groups == ids[j]], ft[groups == ids[j]]) for j in chosen) / 2
    assert close(L.pvkd_affinity(fs, ft, groups, chosen), want)


def test_mgd_reconstructs_the_teacher_from_the_kept_positions(g, device) -> None:
    s = torch.randn(2, 3, 4, 4, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(2, 3, 4, 4, dtype=D, generator=g)
    gen = torch.nn.Conv2d(3, 3, 3, padding=1).to(D)
    keep = torch.rand(2, 1, 4, 4, generator=g) >= 0.5
    want = 0.0
    masked = s * keep  # every channel of a position is masked together
    out = gen(masked)
    for idx in torch.cartesian_prod(*[torch.arange(n) for n in t.shape]):
        want = want + (out[tuple(idx)] - t[tuple(idx)]) ** 2
    want = want / t.numel()
    assert close(L.mgd(s, t, gen, keep=keep), want)
    on_device = copy.deepcopy(gen).to(device)
    on_device_matches(lambda s, t, keep: L.mgd(s, t, on_device, keep=keep), lambda s, t, keep: L.mgd(s, t, gen, keep=keep),
                      (s, t, keep), device)
    torch.manual_seed(3)
    drawn = L.mgd(s, t, gen, mask_ratio=0.65)
    torch.manual_seed(3)
    again = (torch.rand(2, 1, 4, 4) >= 0.65)
    assert close(drawn, L.mgd(s, t, gen, keep=again))
    assert close(L.mgd(s, t, gen, mask_ratio=0.0), ((gen(s) - t) ** 2).mean())
    with pytest.raises(ValueError, match="mask_ratio"):
        L.mgd(s, t, gen, mask_ratio=1.0)


def test_rgo2d_takes_the_class_tables_ignore_label(g) -> None:
    s, t, labels, mask = _rgo_inputs(g)
    labels[labels == 3] = 3  # class 3 present; treat it as the data's ignore label
    as_class = L.rgo2d(s, t, labels, mask)
    ignored = L.rgo2d(s, t, labels, mask, ignore_index=3)
    want = sum(w * sum(naive_rgo2d_region(s, t, torch.where(labels == 3, 255, labels), mask & r))
               for w, r in zip((0.06, 0.15, 0.20), range_regions(tuple(s.shape[2:]), "boxes")))
    assert close(ignored, want) and not close(as_class, ignored)


def test_the_objectives_compute_their_functions_with_the_data_ignore_label(g) -> None:
    """CleanerS, RGO²D, KD read the class table's ignore label from the bound context, not a constant."""
    from dataclasses import replace

    from distilkit.data.batch import Batch
    from distilkit.data.info import ClassTable, DataInfo
    from distilkit.registry import OBJECTIVES
    from distilkit.term import TermContext

    s, t, labels, mask = _rgo_inputs(g)
    batch = Batch({}, {"voxel_target": labels, "scribble": labels}, {"size": 2})
    info = DataInfo(None, replace(ClassTable.semantickitti(), ignore_index=2))
    for name, fn in (("cleaners", lambda: L.cleaners(s, t, labels, ignore_index=2)),
                     ("rgo2d", lambda: L.rgo2d(s, t, labels, (labels != 2) & (labels != 0), ignore_index=2)),
                     ("kd", lambda: L.kd(s, t, 1.0, labels != 2))):
        cls = OBJECTIVES.get(name)
        obj = cls(cls.Params())
        obj.bind(TermContext(torch.nn.Identity(), None, torch.device("cpu"), info=info))
        assert close(obj.compute({"student": s, "teacher": t, **obj.batch_roles(batch)}, batch), fn()), name
