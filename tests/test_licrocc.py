"""LiCROcc's three terms against float64 transcriptions of its release (HR-zju/LiCROcc at 0c1423b,
``projects/mmdet3d_plugin/ssc_rs/detectors/ssc_rs.py``), written here from the release's code — per-sample loops,
``nn.KLDivLoss``, boolean indexing, ``bmm`` of the normalised maps — not from distilkit's: values and gradients, at
several shapes, masks empty and full."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from distilkit.losses.licrocc import licrocc_affinity, licrocc_bev, licrocc_kl

D = torch.float64  # every tensor of these tests
pytestmark = pytest.mark.filterwarnings("ignore:reduction. 'mean' divides")  # the release's KLDivLoss("mean")


def _release_pdd(s, t, target, useful):
    """Distill_1_loss (L403-422): per sample KLDivLoss(mean) of log_softmax(student) against softmax(teacher) over
    the voxels with target not 0 nor 255, times 1 or 1e-5, summed over samples / B."""
    b, c = s.shape[:2]
    log_q = F.log_softmax(s, dim=1).permute(0, 2, 3, 4, 1).reshape(b, -1, c)
    p = F.softmax(t, dim=1).permute(0, 2, 3, 4, 1).reshape(b, -1, c)
    tgt = target.reshape(b, -1)
    total = 0.0
    for i in range(b):
        keep = (tgt[i] != 0) & (tgt[i] != 255)
        loss = nn.KLDivLoss(reduction="mean")(log_q[i][keep].unsqueeze(0), p[i][keep].unsqueeze(0))
        total = total + (1.0 if useful[i] else 1e-5) * loss
    return total / b


def _release_cmrd(students, teachers, masks, useful):
    """Distill_2 (L500-536): per sample and map the mean over the masked cells of 1 - cosine over channels
    (features [C, H, W] indexed by a [H, W] mask), times 1 or 1e-5, summed / (maps x B)."""
    total = 0.0
    b = students[0].shape[0]
    for i in range(b):
        for s, t, m in zip(students, teachers, masks):
            fs, ft = s[i][:, m[i]], t[i][:, m[i]]  # [C, K]
            d = 1 - F.cosine_similarity(fs, ft, dim=0)
            total = total + (1.0 if useful[i] else 1e-5) * d.mean()
    return total / (len(students) * b)


def _release_brd(students, teachers, size):
    """Distill_3 (L540-558) without its x40: per map both resized (bilinear), each model's cosine matrix
    (F.normalize, bmm), F.l1_loss(mean) / B, summed over the maps."""
    total = 0.0
    for s, t in zip(students, teachers):
        b = s.shape[0]
        if size is not None:
            s = F.interpolate(s, size=size, mode="bilinear")
            t = F.interpolate(t, size=size, mode="bilinear")
        gs = F.normalize(s.flatten(2), p=2, dim=1)
        gt = F.normalize(t.flatten(2), p=2, dim=1)
        a_s = torch.bmm(gs.transpose(1, 2), gs)
        a_t = torch.bmm(gt.transpose(1, 2), gt)
        total = total + F.l1_loss(a_s, a_t, reduction="mean") / b
    return total


def _labels(shape, seed, occupied=0.4):
    g = torch.Generator().manual_seed(seed)
    labels = torch.randint(1, 5, shape, generator=g)
    labels[torch.rand(shape, generator=g) > occupied] = 0
    labels[torch.rand(shape, generator=g) < 0.1] = 255
    return labels


@pytest.mark.parametrize("shape", [(1, 5, 4, 4, 2), (3, 4, 6, 4, 3), (2, 17, 3, 5, 4)])
def test_pdd_is_the_release_with_its_scene_weights(shape):
    g = torch.Generator().manual_seed(sum(shape))
    s = torch.randn(shape, generator=g, dtype=D, requires_grad=True)
    t = torch.randn(shape, generator=g, dtype=D)
    labels = _labels(shape[:1] + shape[2:], sum(shape))
    useful = [i % 2 == 0 for i in range(shape[0])]
    weights = torch.tensor([1.0 if u else 1e-5 for u in useful], dtype=D)
    ours = licrocc_kl(s, t, labels, weights)
    theirs = _release_pdd(s, t, labels, useful)
    assert torch.allclose(ours, theirs, rtol=1e-12, atol=1e-14)
    (g_ours,) = torch.autograd.grad(ours, s)
    (g_theirs,) = torch.autograd.grad(theirs, s)
    assert torch.allclose(g_ours, g_theirs, rtol=1e-10, atol=1e-14)
    assert torch.allclose(licrocc_kl(s, t, labels), _release_pdd(s, t, labels, [True] * shape[0]), rtol=1e-12)
    assert torch.autograd.gradcheck(lambda x: licrocc_kl(x, t, labels, weights), (s,))


def test_pdd_masks_empty_and_full():
    s, t = torch.randn(2, 3, 2, 2, 2, dtype=D), torch.randn(2, 3, 2, 2, 2, dtype=D)
    full = torch.ones(2, 2, 2, 2, dtype=torch.long)
    assert torch.allclose(licrocc_kl(s, t, full), _release_pdd(s, t, full, [True, True]), rtol=1e-12)
    empty = full.clone()
    empty[1] = 0  # the release's mean over no voxel is NaN: here the sample gives 0
    assert torch.isnan(_release_pdd(s, t, empty, [True, True]))
    assert torch.allclose(licrocc_kl(s, t, empty), _release_pdd(s[:1], t[:1], full[:1], [True]) / 2, rtol=1e-12)


@pytest.mark.parametrize("sizes", [[(4, 4)], [(8, 8), (4, 4), (2, 2)], [(6, 4), (3, 2)]])
def test_cmrd_is_the_release_over_its_maps_and_samples(sizes):
    g = torch.Generator().manual_seed(len(sizes))
    b = 3
    students = [torch.randn(b, 4 * (i + 1), h, w, generator=g, dtype=D, requires_grad=True) for i, (h, w) in enumerate(sizes)]
    teachers = [torch.randn(b, 4 * (i + 1), h, w, generator=g, dtype=D) for i, (h, w) in enumerate(sizes)]
    masks = [torch.rand(b, h, w, generator=g) < 0.5 for h, w in sizes]
    for m in masks:
        m[:, 0, 0] = True  # no sample without a cell (the release's NaN)
    masks[0][1] = True  # one sample's mask full
    useful = [True, False, True]
    weights = torch.tensor([1.0, 1e-5, 1.0], dtype=D)
    ours = licrocc_bev(students, teachers, masks, weights)
    theirs = _release_cmrd(students, teachers, masks, useful)
    assert torch.allclose(ours, theirs, rtol=1e-12)
    g_ours = torch.autograd.grad(ours, students)
    g_theirs = torch.autograd.grad(theirs, students)
    assert all(torch.allclose(a, b_, rtol=1e-10, atol=1e-15) for a, b_ in zip(g_ours, g_theirs))
    assert torch.autograd.gradcheck(lambda x: licrocc_bev([x], teachers[:1], masks[:1]), (students[0],))
    # any mask the objective builds (its transpose_mask: tests/test_bev_taps.py) is read as the release reads it
    if sizes[0][0] == sizes[0][1]:
        flipped = [m.transpose(1, 2) for m in masks]
        assert torch.allclose(licrocc_bev(students, teachers, flipped), _release_cmrd(students, teachers, flipped,
                                                                                      [True] * b), rtol=1e-12)


def test_cmrd_without_a_cell_gives_zero_where_the_release_gives_nan():
    s, t = torch.randn(2, 3, 4, 4, dtype=D), torch.randn(2, 3, 4, 4, dtype=D)
    mask = torch.zeros(2, 4, 4, dtype=torch.bool)
    mask[0, 1, 2] = True
    assert torch.isnan(_release_cmrd([s], [t], [mask], [True, True]))
    expected = (1 - F.cosine_similarity(s[0, :, 1, 2], t[0, :, 1, 2], dim=0)) / 2
    assert torch.allclose(licrocc_bev([s], [t], [mask]), expected, rtol=1e-12)


@pytest.mark.parametrize("size", [(4, 4), None])
def test_brd_is_the_release_with_and_without_its_second_division_by_b(size):
    g = torch.Generator().manual_seed(7)
    b = 3
    students = [torch.randn(b, 6, 8, 8, generator=g, dtype=D, requires_grad=True),
                torch.randn(b, 5, 4, 4, generator=g, dtype=D, requires_grad=True)]
    teachers = [torch.randn(b, 3, 8, 8, generator=g, dtype=D), torch.randn(b, 7, 4, 4, generator=g, dtype=D)]
    if size is None:
        students, teachers = students[1:], teachers[1:]
    ours = licrocc_affinity(students, teachers, size=size, release_batch=True)
    theirs = _release_brd(students, teachers, size)
    assert torch.allclose(ours, theirs, rtol=1e-10)
    assert torch.allclose(licrocc_affinity(students, teachers, size=size), theirs * b, rtol=1e-10)
    g_ours = torch.autograd.grad(ours, students)
    g_theirs = torch.autograd.grad(theirs, students)
    assert all(torch.allclose(a, c, rtol=1e-8, atol=1e-12) for a, c in zip(g_ours, g_theirs))


def test_brd_zero_cells_and_the_shapes_it_refuses():
    s = torch.randn(1, 4, 4, 4, dtype=D)
    t = torch.randn(1, 3, 4, 4, dtype=D)
    s[0, :, 0, 0] = 0  # a zero cell: its cosines are 0 on both sides where the release's are
    assert torch.allclose(licrocc_affinity([s], [t], size=None), _release_brd([s], [t], None), rtol=1e-10)
    with pytest.raises(ValueError, match="differ in size"):
        licrocc_affinity([s], [torch.randn(1, 3, 8, 8, dtype=D)], size=None)
    with pytest.raises(ValueError, match="as many teacher maps"):
        licrocc_affinity([s], [])
