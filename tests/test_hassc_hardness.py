"""HASSC's hardness-aware terms (distilkit.losses.hardness, the hassc_ce task loss and the hassc_hvm objective)
against naive float64 voxel-by-voxel references of the release's formulas, values and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from distilkit.losses.hardness import (geometry_weighted_ce, hard_voxel_ce, local_geometric_anisotropy,
                                       sample_hard_voxels, voxel_sample)

NEIGHBOURS = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]


def naive_lga(labels: torch.Tensor) -> torch.Tensor:
    b, x, y, z = labels.shape
    out = torch.zeros(b, x, y, z, dtype=torch.float64)
    for n in range(b):
        for i in range(x):
            for j in range(y):
                for k in range(z):
                    c = int(labels[n, i, j, k])
                    if c == 255:
                        continue
                    for di, dj, dk in NEIGHBOURS:
                        a, bb, cc = i + di, j + dj, k + dk
                        if 0 <= a < x and 0 <= bb < y and 0 <= cc < z:
                            other = int(labels[n, a, bb, cc])
                            out[n, i, j, k] += other != 255 and other != c
    return out


def naive_ce(z: torch.Tensor, y: int) -> torch.Tensor:
    return -(z[y] - torch.logsumexp(z, 0))


def naive_trilinear(volume: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(C,) value of a (C, X, Y, Z) volume at c in [0,1)^3: index c·size − ½, zero outside (align_corners=False)."""
    size = volume.shape[1:]
    p = [float(c[d]) * size[d] - 0.5 for d in range(3)]
    lo = [math.floor(v) for v in p]
    out = torch.zeros(volume.shape[0], dtype=volume.dtype)
    for corner in range(8):
        idx, w = [], 1.0
        for d in range(3):
            up = (corner >> d) & 1
            idx.append(lo[d] + up)
            frac = p[d] - lo[d]
            w *= frac if up else 1 - frac
        if all(0 <= idx[d] < size[d] for d in range(3)):
            out = out + w * volume[:, idx[0], idx[1], idx[2]]
    return out


def naive_nearest(volume: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    size = volume.shape[1:]
    idx = [min(int(float(c[d]) * size[d]), size[d] - 1) for d in range(3)]
    return volume[:, idx[0], idx[1], idx[2]]


def labels_with_structure(b=2, shape=(4, 5, 3), classes=4, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, classes, (b, *shape), generator=g)
    labels[torch.rand(labels.shape, generator=g) < 0.15] = 255
    return labels


def test_lga_counts_the_face_neighbours_with_another_label() -> None:
    labels = labels_with_structure()
    assert torch.equal(local_geometric_anisotropy(labels).double(), naive_lga(labels))
    flat = torch.zeros(1, 3, 3, 3, dtype=torch.long)
    assert local_geometric_anisotropy(flat).sum() == 0
    flat[0, 1, 1, 1] = 2  # a voxel alone: 6 differing neighbours, each of them 1
    lga = local_geometric_anisotropy(flat)
    assert lga[0, 1, 1, 1] == 6 and lga.sum() == 12
    with pytest.raises(ValueError, match=r"\(B, \*spatial\)"):
        local_geometric_anisotropy(torch.zeros(3))


@pytest.mark.parametrize("reduce", ["per_sample", "pooled"])
def test_geometry_weighted_ce_equals_the_naive_mean_over_valid_voxels(reduce, device) -> None:
    labels = labels_with_structure()
    logits = torch.randn(2, 4, 4, 5, 3, dtype=torch.float64, requires_grad=True)
    weights = torch.tensor([0.4, 0.6, 0.8, 0.7], dtype=torch.float64)
    lga = naive_lga(labels)
    terms: list[list[torch.Tensor]] = [[], []]
    for n, i, j, k in (labels != 255).nonzero().tolist():
        y = int(labels[n, i, j, k])
        terms[n].append(weights[y] * naive_ce(logits[n, :, i, j, k], y) * (1 + lga[n, i, j, k]))
    naive = (torch.stack(terms[0]).mean() + torch.stack(terms[1]).mean()) / 2 if reduce == "per_sample" else \
        torch.stack(terms[0] + terms[1]).mean()
    ours = geometry_weighted_ce(logits, labels, weights, lga, reduce=reduce)
    torch.testing.assert_close(ours, naive, rtol=1e-12, atol=0)
    g_ours, = torch.autograd.grad(ours, logits)
    g_naive, = torch.autograd.grad(naive, logits)
    torch.testing.assert_close(g_ours, g_naive, rtol=1e-10, atol=1e-14)
    assert torch.autograd.gradcheck(lambda z: geometry_weighted_ce(z, labels, weights, lga, reduce=reduce), (logits,),
                                    fast_mode=True)
    gpu = geometry_weighted_ce(logits.detach().float().to(device), labels.to(device), weights.float().to(device),
                               lga.float().to(device), reduce=reduce)
    torch.testing.assert_close(gpu.double().cpu(), naive.detach(), rtol=1e-5, atol=0)
    none = torch.full_like(labels, 255)
    assert geometry_weighted_ce(logits, none, weights, lga, reduce=reduce).item() == 0.0


def test_voxel_sample_reads_trilinearly_and_nearest_at_the_positions() -> None:
    g = torch.Generator().manual_seed(1)
    volume = torch.randn(2, 3, 4, 5, 3, dtype=torch.float64, generator=g)
    coords = torch.rand(2, 7, 3, dtype=torch.float64, generator=g)
    tri, near = voxel_sample(volume, coords), voxel_sample(volume, coords, "nearest")
    for n in range(2):
        for i in range(7):
            torch.testing.assert_close(tri[n, :, i], naive_trilinear(volume[n], coords[n, i]), rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(near[n, :, i], naive_nearest(volume[n], coords[n, i]))


@pytest.mark.parametrize("rank", ["probabilities", "logits"])
def test_each_sample_keeps_its_own_hardest_draws_then_uniform_ones(rank: str) -> None:
    """B = 2 with different predictions: sample 1's kept positions are its own hardest (the release gathers them from
    the flattened batch with per-sample indices)."""
    g = torch.Generator().manual_seed(2)
    coarse = torch.randn(2, 4, 4, 5, 3, generator=g) * 3
    n, t, omega = 8, 3, 0.75
    torch.manual_seed(5)
    got = sample_hard_voxels(coarse, n, t, omega, rank)
    torch.manual_seed(5)
    draws = torch.rand(2, t * n, 3)
    uniform = torch.rand(2, n - int(omega * n), 3)
    for s in range(2):
        hardness = []
        for i in range(t * n):
            if rank == "logits":
                v = naive_trilinear(coarse[s].double().sort(0, descending=True)[0], draws[s, i].double())
                top = v[:2]
            else:
                top = naive_trilinear(coarse[s].double(), draws[s, i].double()).softmax(0).sort(descending=True)[0]
            hardness.append(1.0 / float(top[0] - top[1]))
        want = sorted(range(t * n), key=lambda i: -hardness[i])[:int(omega * n)]
        kept = got[s, :int(omega * n)]
        assert sorted(map(tuple, kept.tolist())) == sorted(tuple(draws[s, i].tolist()) for i in want)
        assert torch.equal(got[s, int(omega * n):], uniform[s])
    assert got.shape == (2, n, 3) and float(got.min()) >= 0 and float(got.max()) < 1


def naive_hvm(logits, labels, lga, weights, alpha, beta, reduce="pooled") -> torch.Tensor:
    """Σ CE (α + β LGA) / Σ w_y over the valid positions: per sample then the mean over the samples (``per_sample``,
    the release's one sample per GPU) or both sums over the batch (``pooled``)."""
    b, _, n = logits.shape
    if reduce == "per_sample":
        return sum(naive_hvm(logits[s:s + 1], labels[s:s + 1], lga[s:s + 1], weights, alpha, beta) for s in range(b)) / b
    num, den = 0.0, 0.0
    for s in range(b):
        for i in range(n):
            y = int(labels[s, i])
            if y == 255:
                continue
            num = num + naive_ce(logits[s, :, i], y) * (alpha + beta * float(lga[s, i]))
            den = den + float(weights[y])
    return num / den


def test_hard_voxel_ce_equals_the_naive_normalised_sum(device) -> None:
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(2, 4, 9, dtype=torch.float64, generator=g, requires_grad=True)
    labels = torch.randint(0, 4, (2, 9), generator=g)
    labels[0, :3] = 255
    lga = torch.randint(0, 7, (2, 9), generator=g).double()
    weights = torch.tensor([0.4, 0.6, 0.8, 0.7], dtype=torch.float64)
    naive = naive_hvm(logits, labels, lga, weights, 0.2, 1.0)
    ours = hard_voxel_ce(logits, labels, lga, weights, 0.2, 1.0, reduce="pooled")
    torch.testing.assert_close(ours, naive, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(ours, logits)[0], torch.autograd.grad(naive, logits)[0],
                               rtol=1e-10, atol=1e-14)
    assert torch.autograd.gradcheck(lambda z: hard_voxel_ce(z, labels, lga, weights, reduce="pooled"), (logits,))
    on = hard_voxel_ce(logits.detach().float().to(device), labels.to(device), lga.float().to(device),
                       weights.float().to(device), reduce="pooled")
    torch.testing.assert_close(on.double().cpu(), naive.detach(), rtol=1e-5, atol=0)


@pytest.mark.parametrize("reduce", ["per_sample", "pooled"])
def test_the_objective_equals_the_naive_composition_of_both_branches(reduce, device) -> None:
    """hassc_hvm on the device: its value and the gradients into the student's prediction and features equal a naive
    float64 composition (the same random draws, naive sampling, hardness, head and normaliser)."""
    from distilkit.objectives.hassc import HardVoxelParams, HASSCHardVoxels

    g = torch.Generator().manual_seed(4)
    k, c = 4, 3
    labels = labels_with_structure(classes=k, seed=4)
    labels[0, 0, 0, 0] = 255
    student = torch.randn(2, k, 4, 5, 3, generator=g) * 2
    feats = torch.randn(2, c, 2, 3, 2, generator=g)  # another resolution: read at the same positions
    teacher = torch.randn(2, k, 4, 5, 3, generator=g) * 2
    params = HardVoxelParams(points=6, oversample=2, omega=0.5, delta=0.1, reduce=reduce)
    obj = HASSCHardVoxels(params)
    obj.setup({"student": student, "features": feats}, None)
    obj.class_weight = torch.tensor([0.4, 0.6, 0.8, 0.7])
    obj.to(device).double() if device.type == "cpu" else obj.to(device)
    dtype = torch.float64 if device.type == "cpu" else torch.float32
    s = student.to(device, dtype).requires_grad_(True)
    f = feats.to(device, dtype).requires_grad_(True)
    torch.manual_seed(9)
    ours = obj.compute({"student": s, "features": f, "teacher": teacher.to(device, dtype),
                        "target": labels.to(device)}, None)
    gs, gf = torch.autograd.grad(ours, (s, f))

    torch.manual_seed(9)
    draws = [torch.rand(2, 12, 3, device=device).cpu(), torch.rand(2, 3, 3, device=device).cpu(),
             torch.rand(2, 12, 3, device=device).cpu(), torch.rand(2, 3, 3, device=device).cpu()]
    s64 = student.double().requires_grad_(True)
    f64 = feats.double().requires_grad_(True)
    w = obj.head.weight.detach().double().cpu()[:, :, 0]
    bias = obj.head.bias.detach().double().cpu()
    lga = naive_lga(labels)
    weights = obj.class_weight.double().cpu()

    def positions(pred, hard, rest):
        out = []
        for smp in range(2):
            hardness = []
            for i in range(hard.shape[1]):
                top = naive_trilinear(pred[smp].double(), hard[smp, i].double()).softmax(0).sort(descending=True)[0]
                hardness.append(1.0 / float(top[0] - top[1]))
            keep = sorted(range(hard.shape[1]), key=lambda i: -hardness[i])[:3]
            out.append([hard[smp, i].double() for i in keep] + [rest[smp, i].double() for i in range(3)])
        return out

    def truth(pos):
        lab = torch.tensor([[int(naive_nearest(labels[smp][None].double(), q)[0]) for q in pos[smp]]
                            for smp in range(2)])
        lg = torch.tensor([[float(naive_nearest(lga[smp][None], q)[0]) for q in pos[smp]] for smp in range(2)])
        return lab, lg

    mine = positions(student, draws[0], draws[1])
    refined = torch.stack([torch.stack([w @ torch.cat([naive_trilinear(s64[smp], q), naive_trilinear(f64[smp], q)])
                                        + bias for q in mine[smp]], 1) for smp in range(2)])
    lab, lg = truth(mine)
    naive = naive_hvm(refined, lab, lg, weights, 0.2, 1.0, reduce)
    theirs = positions(teacher, draws[2], draws[3])
    at = torch.stack([torch.stack([naive_nearest(s64[smp], q) for q in theirs[smp]], 1) for smp in range(2)])
    lab, lg = truth(theirs)
    naive = naive + 0.1 * naive_hvm(at, lab, lg, weights, 0.2, 1.0, reduce)
    ns, nf = torch.autograd.grad(naive, (s64, f64))
    rel = 1e-10 if device.type == "cpu" else 1e-4
    torch.testing.assert_close(ours.double().cpu(), naive.detach(), rtol=rel, atol=0)
    torch.testing.assert_close(gs.double().cpu(), ns, rtol=rel, atol=rel * 1e-3)
    torch.testing.assert_close(gf.double().cpu(), nf, rtol=rel, atol=rel * 1e-3)
    assert float(ns.abs().sum()) > 0 and float(nf.abs().sum()) > 0


def test_the_release_class_weights_need_semantickittis_classes() -> None:
    from distilkit.losses.ssc import RELEASE_WEIGHTS_SEMANTICKITTI, class_weights, log_frequency_weights

    table = class_weights("release", None, 20)
    assert table.tolist() == pytest.approx(list(RELEASE_WEIGHTS_SEMANTICKITTI))
    with pytest.raises(ValueError, match="20 classes; the data has 5"):
        class_weights("release", None, 5)
    assert torch.equal(class_weights("none", None, 3), torch.ones(3))
    # the table is VoxFormer's 10 / ln(f + 0.001) on SemanticKITTI's counts: empty (5.4e9 voxels) -> 0.446
    assert float(log_frequency_weights(torch.tensor([5.41773033e09]))[0]) == pytest.approx(0.446, abs=5e-4)
