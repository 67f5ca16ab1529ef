"""The height collapse and the voxel-to-BEV terms against float64 transcriptions of the release
(fengjiang5/Knowledge-Distillation-from-Cylinder3D-to-PolarNet at b5f136e: ``kd/cross_attn_spconv121.py``'s
column max, ``kd/weight_mse.py``, ``train_SemanticKITTI.py``'s class weights), written here from its code — a loop
over the columns, ``MSELoss``, the weighted sum and its root — not from distilkit's: values and gradients."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from distilkit.losses.bev import bev_from_voxels, collapse_height, column_weights
from distilkit.structures import SparseVoxels

D = torch.float64


def _sparse(b, shape, n, channels, seed):
    g = torch.Generator().manual_seed(seed)
    cells = torch.randperm(b * shape[0] * shape[1] * shape[2], generator=g)[:n]
    coords = torch.stack([cells // (shape[0] * shape[1] * shape[2]), cells // (shape[1] * shape[2]) % shape[0],
                          cells // shape[2] % shape[1], cells % shape[2]], dim=1)
    return SparseVoxels(coords, torch.randn(n, channels, generator=g, dtype=D, requires_grad=True), shape)


def _release_column_max(voxels, b):
    """The release's scatter_max over each (batch, x, y) column of the active voxels onto a zero canvas."""
    x, y = voxels.spatial_shape[:2]
    out = torch.zeros(b, voxels.feats.shape[1], x, y, dtype=voxels.feats.dtype)
    columns = {}
    for row, (bb, i, j, _) in enumerate(voxels.coords.tolist()):
        columns.setdefault((bb, i, j), []).append(row)
    for (bb, i, j), rows in columns.items():
        out[bb, :, i, j] = voxels.feats[rows].max(dim=0).values
    return out


@pytest.mark.parametrize("b,shape,n", [(1, (4, 4, 3), 20), (2, (5, 3, 4), 40), (3, (2, 2, 6), 24)])
def test_sparse_column_max_is_the_release(b, shape, n):
    voxels = _sparse(b, shape, n, 5, n)
    ours = collapse_height(voxels, "max", batch=b)
    theirs = _release_column_max(voxels, b)
    assert torch.equal(ours, theirs)
    w = torch.randn_like(ours)
    (g_ours,) = torch.autograd.grad((ours * w).sum(), voxels.feats)
    (g_theirs,) = torch.autograd.grad((theirs * w).sum(), voxels.feats)
    assert torch.allclose(g_ours, g_theirs)


def test_sparse_column_mean_and_dense_collapses():
    voxels = _sparse(2, (3, 3, 4), 30, 4, 3)
    mean = collapse_height(voxels, "mean", batch=2)
    for bb, i, j in {(r[0], r[1], r[2]) for r in voxels.coords.tolist()}:
        rows = [(c[0], c[1], c[2]) == (bb, i, j) for c in voxels.coords.tolist()]
        assert torch.allclose(mean[bb, :, i, j], voxels.feats[torch.tensor(rows)].mean(0))
    assert int((mean.abs().sum(1) > 0).sum()) == len({tuple(r[:3]) for r in voxels.coords.tolist()})  # empty: 0
    dense = torch.randn(2, 3, 4, 5, 6, dtype=D)
    assert torch.equal(collapse_height(dense, "max"), dense.max(dim=4).values)
    assert torch.allclose(collapse_height(dense, "mean"), dense.mean(dim=4))
    with pytest.raises(ValueError, match="max or mean"):
        collapse_height(dense, "sum")
    with pytest.raises(ValueError, match="SparseVoxels"):
        collapse_height(torch.randn(2, 3, 4, 5), "max")


def _release_alpha(freq):
    """train_SemanticKITTI.py L70-78 and L176: 1 / (f + 0.001), / 50."""
    return 1 / (freq + 0.001) / 50


def _release_lwd(teacher, student, labels, alpha):
    """weight_mse.py L11-17: W = the column's sum of alpha[label]; sqrt(sum(W * sum_c (T - S)^2) / (B H W))."""
    weight = alpha[labels].sum(dim=-1)
    d = ((teacher - student) ** 2).sum(dim=1)
    b, h, w = weight.shape
    return torch.sqrt(torch.sum(weight * d) / (b * h * w))


@pytest.mark.parametrize("shape", [(1, 4, 6, 6, 5), (2, 3, 4, 5, 8)])
def test_label_weighted_distance_is_the_release(shape):
    b, c, h, w, z = shape
    g = torch.Generator().manual_seed(h * w)
    s = torch.randn(b, c, h, w, generator=g, dtype=D, requires_grad=True)
    t = torch.randn(b, c, h, w, generator=g, dtype=D, requires_grad=True)
    labels = torch.randint(0, 6, (b, h, w, z), generator=g)
    freq = torch.rand(6, generator=g, dtype=D)
    freq = freq / freq.sum()
    alpha = _release_alpha(freq)
    weights = column_weights(labels, alpha)
    ours = bev_from_voxels(s, t, weights)
    theirs = _release_lwd(t, s, labels, alpha)
    assert torch.allclose(ours, theirs, rtol=1e-12)
    g_ours = torch.autograd.grad(ours, (s, t))
    g_theirs = torch.autograd.grad(theirs, (s, t))
    assert all(torch.allclose(a, c_, rtol=1e-10) for a, c_ in zip(g_ours, g_theirs))  # the target trains too
    assert torch.allclose(bev_from_voxels(s, t, weights, root=False), theirs ** 2, rtol=1e-12)
    assert torch.allclose(bev_from_voxels(s, t), nn.MSELoss()(t, s), rtol=1e-12)  # VPD: the plain mean
    assert torch.autograd.gradcheck(lambda x: bev_from_voxels(x, t.detach(), weights), (s,))


def test_column_weights_ignore_coarser_planes_and_errors():
    labels = torch.tensor([[[[0, 1, 255], [2, 2, 2]], [[0, 0, 0], [1, 0, 0]]]])  # (1, 2, 2, 3)
    alpha = torch.tensor([0.5, 2.0, 7.0], dtype=D)
    got = column_weights(labels, alpha)
    assert torch.equal(got, torch.tensor([[[0.5 + 2 + 0.5, 21.0], [1.5, 3.0]]], dtype=D))  # 255 weighs as empty
    assert torch.allclose(column_weights(labels, alpha, (1, 1)), got.mean().reshape(1, 1, 1))
    with pytest.raises(ValueError, match="integer multiple"):
        column_weights(labels, alpha, (3, 1))
    with pytest.raises(ValueError, match="no class weight"):
        column_weights(labels + 3 * (labels == 2), alpha)
    with pytest.raises(ValueError, match="one"):
        bev_from_voxels(torch.randn(1, 2, 3, 3), torch.randn(1, 2, 3, 4))


def test_the_root_has_a_finite_gradient_at_a_perfect_match():
    s = torch.randn(1, 2, 3, 3, dtype=D, requires_grad=True)
    value = bev_from_voxels(s, s.detach().clone(), torch.ones(1, 3, 3, dtype=D))
    (grad,) = torch.autograd.grad(value, s)
    assert torch.isfinite(grad).all() and value < 1e-150
