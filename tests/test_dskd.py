"""DSKD (SCPNet eq. 1-2) against a naive float64 N x N implementation (the fast form on the device of ``--device``, the
naive one on the CPU)."""

from __future__ import annotations

import importlib

import pytest
import torch

import distilkit.losses as L
from distilkit.data.batch import Batch
from distilkit.geometry.voxel import align_sparse
from distilkit.objectives.dskd import DSKD, DSKDParams
from distilkit.taps import SparseVoxels

dskd_module = importlib.import_module("distilkit.losses.dskd")  # the module (L.dskd is the function)


def naive_dskd(fs: torch.Tensor, ft: torch.Tensor) -> torch.Tensor:
    """Eq. 1-2 literally: cosine matrices P_S, P_T and the mean of (P_S - P_T)^2 over N^2 pairs."""
    n = fs.shape[0]
    ps = torch.zeros(n, n, dtype=torch.float64)
    pt = torch.zeros(n, n, dtype=torch.float64)
    ns, nt = fs.norm(dim=1), ft.norm(dim=1)
    for i in range(n):
        for j in range(n):
            if ns[i] > 0 and ns[j] > 0:
                ps[i, j] = fs[i] @ fs[j] / (ns[i] * ns[j])
            if nt[i] > 0 and nt[j] > 0:
                pt[i, j] = ft[i] @ ft[j] / (nt[i] * nt[j])
    return ((ps - pt) ** 2).sum() / n**2


# more rows than the widths together (N > cs + ct: the Gram forms are not full rank), widths either way round; the
# naive reference loops over N^2 pairs in Python, so N stays small
@pytest.mark.parametrize("n,cs,ct", [(1, 3, 3), (7, 4, 4), (20, 8, 5), (24, 3, 16)])
def test_value_and_gradient_match_naive(n: int, cs: int, ct: int, device) -> None:
    g = torch.Generator().manual_seed(n)
    fs = torch.randn(n, cs, dtype=torch.float64, generator=g, requires_grad=True)
    ft = torch.randn(n, ct, dtype=torch.float64, generator=g, requires_grad=True)
    on = [f.detach().to(device).requires_grad_() for f in (fs, ft)]
    fast = L.dskd(*on)
    ga, gb = (x.cpu() for x in torch.autograd.grad(fast, on))
    slow = naive_dskd(fs, ft)
    na, nb = torch.autograd.grad(slow, (fs, ft))
    assert torch.allclose(fast.cpu(), slow, rtol=1e-6, atol=1e-12)
    assert (ga - na).norm() <= 1e-6 * na.norm() + 1e-12
    assert (gb - nb).norm() <= 1e-6 * nb.norm() + 1e-12


def test_zero_teacher_rows_count_as_zero_similarity() -> None:
    g = torch.Generator().manual_seed(1)
    fs = torch.randn(12, 5, dtype=torch.float64, generator=g, requires_grad=True)
    ft = torch.randn(12, 5, dtype=torch.float64, generator=g)
    ft[[2, 5, 11]] = 0.0
    fast = L.dskd(fs, ft)
    assert torch.allclose(fast, naive_dskd(fs, ft), rtol=1e-6)
    (grad,) = torch.autograd.grad(fast, fs)
    assert torch.isfinite(grad).all()


@pytest.mark.parametrize("ct", [6, 4])  # unequal widths, and the S/D form of equal widths
def test_gradcheck(ct: int, device) -> None:
    g = torch.Generator().manual_seed(2)
    fs = torch.randn(9, 4, dtype=torch.float64, generator=g).to(device).requires_grad_()
    ft = torch.randn(9, ct, dtype=torch.float64, generator=g).to(device).requires_grad_()
    assert torch.autograd.gradcheck(L.dskd, (fs, ft))


def test_identical_features_give_zero_and_scale_invariance() -> None:
    f = torch.randn(30, 8, dtype=torch.float64)
    assert L.dskd(f, f).item() == pytest.approx(0.0, abs=1e-14)
    # cosine similarity ignores a per-row positive scale
    s = torch.rand(30, 1, dtype=torch.float64) + 0.1
    assert L.dskd(f * s, f).item() == pytest.approx(0.0, abs=1e-12)


def test_float32_large_n_stays_accurate() -> None:
    # the float64 Gram accumulation keeps float32 inputs accurate where the terms are O(N^2)
    g = torch.Generator().manual_seed(3)
    fs = torch.randn(3000, 8, generator=g)
    ft = fs + 0.05 * torch.randn(3000, 8, generator=g)
    a = fs.double() / fs.double().norm(dim=1, keepdim=True)
    b = ft.double() / ft.double().norm(dim=1, keepdim=True)
    exact = ((a @ a.T - b @ b.T) ** 2).mean()
    assert L.dskd(fs, ft).double().item() == pytest.approx(exact.item(), rel=1e-5)


def test_bad_shapes_are_named() -> None:
    with pytest.raises(ValueError, match="same N voxels"):
        L.dskd(torch.randn(4, 3), torch.randn(5, 3))
    with pytest.raises(ValueError, match=r"\(N, C\)"):
        L.dskd(torch.randn(4, 3, 2), torch.randn(4, 3))


def test_empty_is_zero() -> None:
    out = L.dskd(torch.zeros(0, 4, requires_grad=True), torch.zeros(0, 4))
    assert out.item() == 0.0


def test_alignment_gathers_teacher_at_student_coords() -> None:
    student = torch.tensor([[0, 1, 2, 3], [0, 4, 4, 1], [1, 1, 2, 3], [0, 9, 9, 0]])
    t_coords = torch.tensor([[1, 1, 2, 3], [0, 1, 2, 3], [0, 5, 5, 5], [0, 4, 4, 1]])
    t_feats = torch.arange(8, dtype=torch.float32).view(4, 2) + 1
    feats, found = align_sparse(student, SparseVoxels(t_coords, t_feats, (10, 10, 10)))
    # naive lookup
    table = {tuple(c.tolist()): f for c, f in zip(t_coords, t_feats)}
    for row, c in enumerate(student):
        expect = table.get(tuple(c.tolist()), torch.zeros(2))
        assert torch.equal(feats[row], expect)
        assert bool(found[row]) == (tuple(c.tolist()) in table)


def test_objective_per_sample_mean() -> None:
    g = torch.Generator().manual_seed(4)
    coords = torch.tensor([[0, 0, 0, 0], [0, 1, 0, 0], [0, 2, 0, 0], [1, 0, 0, 0], [1, 3, 0, 0]])
    fs = torch.randn(5, 3, generator=g, dtype=torch.float64)
    ft = torch.randn(5, 3, generator=g, dtype=torch.float64)
    obj = DSKD(DSKDParams())
    val = obj(SparseVoxels(coords, fs, (4, 1, 1)), SparseVoxels(coords, ft, (4, 1, 1)), Batch({}, {}, {"size": 1}))
    expect = (naive_dskd(fs[:3], ft[:3]) + naive_dskd(fs[3:], ft[3:])) / 2
    assert val.item() == pytest.approx(expect.item(), rel=1e-9)


@pytest.mark.parametrize("ct", [5, 3])
def test_several_row_blocks_match_naive(monkeypatch: pytest.MonkeyPatch, ct: int, device) -> None:
    # blocks of 8 rows over 19 rows (8 + 8 + 3): partial last block, Gram sums and gradients across blocks
    monkeypatch.setattr(dskd_module, "_BLOCK", 8)
    g = torch.Generator().manual_seed(4)
    fs = torch.randn(19, 3, dtype=torch.float64, generator=g, requires_grad=True)
    ft = torch.randn(19, ct, dtype=torch.float64, generator=g, requires_grad=True)
    on = [f.detach().to(device).requires_grad_() for f in (fs, ft)]
    fast = L.dskd(*on)
    slow = naive_dskd(fs, ft)
    assert torch.allclose(fast.cpu(), slow, rtol=1e-9, atol=1e-14)
    for a, b in zip(torch.autograd.grad(fast, on), torch.autograd.grad(slow, (fs, ft))):
        assert (a.cpu() - b).norm() <= 1e-9 * b.norm()
