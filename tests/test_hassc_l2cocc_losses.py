"""HASSC's KD and L2COcc's PAD, FSD and relational terms as plain functions, against naive float64 references
written voxel by voxel from the releases' formulas (HASSC utils/ssc_loss.py; L2COcc CameraSegmentor.py), values and
gradients, on the device of --device (references on the CPU); the relation term's row blocks against the dense
P x P form."""

from __future__ import annotations

import math

import pytest
import torch

import distilkit.losses as L
from conftest import on_device_matches
from distilkit.losses import l2cocc as l2

D = torch.float64


def rand(*shape, g, grad=True):
    return torch.randn(*shape, dtype=D, generator=g).requires_grad_(grad)


def labels_of(b, spatial, g, k=4):
    lab = torch.randint(0, k, (b, *spatial), generator=g)
    lab[torch.rand(b, *spatial, generator=g) < 0.2] = 255
    return lab


def naive_kl_of_sample(s, t, labels, temp, i):
    """Sample i's mean over its valid voxels of T^2 KL(p_T || p_S), voxel by voxel (the release's distill_ssc_loss
    on one sample); 0 without a valid voxel."""
    vals = []
    for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
        idx = tuple(idx) if isinstance(idx, list) else (idx,)
        if int(labels[(i, *idx)]) == 255:
            continue
        zs, zt = s[(i, slice(None), *idx)] / temp, t[(i, slice(None), *idx)] / temp
        ps, pt = torch.softmax(zs, 0), torch.softmax(zt, 0)
        vals.append(sum(pt[k] * (torch.log(pt[k]) - torch.log(ps[k])) for k in range(len(pt))) * temp ** 2)
    return sum(vals) / len(vals) if vals else torch.zeros((), dtype=D)


def naive_hassc(s, t, labels, temp, miou):
    """mean_b exp(miou_b) KL_b: ``miou`` None (weight 1), a float (one weight) or a list (one per sample, the
    release's one sample per GPU averaged by DDP)."""
    weights = [0.0] * s.shape[0] if miou is None else miou if isinstance(miou, list) else [miou] * s.shape[0]
    return sum(naive_kl_of_sample(s, t, labels, temp, i) * math.exp(w) for i, w in enumerate(weights)) / s.shape[0]


@pytest.mark.parametrize("temp,miou", [(1.0, None), (2.5, 0.3), (1.5, [0.2, 0.45])])
def test_hassc_kd_is_the_per_sample_mean_of_the_valid_voxels_kl(temp, miou, device) -> None:
    g = torch.Generator().manual_seed(0)
    s, t = rand(2, 4, 3, 2, 2, g=g), rand(2, 4, 3, 2, 2, g=g)
    lab = labels_of(2, (3, 2, 2), g)
    weight = torch.tensor(miou, dtype=D) if isinstance(miou, list) else miou
    on_device_matches(lambda s, t, lab: L.hassc_kd(s, t, lab, temp, weight),
                      lambda s, t, lab: naive_hassc(s, t, lab, temp, miou), (s, t, lab), device, rel=1e-9)
    lab[1] = 255  # a sample without a valid voxel gives 0 and still counts in the batch mean
    assert math.isclose(L.hassc_kd(s, t, lab, temp).item(), naive_hassc(s, t, lab, temp, None).item(), rel_tol=1e-9)
    with pytest.raises(ValueError, match="labels"):
        L.hassc_kd(s, t, lab[:, :1])
    with pytest.raises(ValueError, match="one value per sample"):
        L.hassc_kd(s, t, lab, temp, torch.zeros(3))


def release_miou(pred, gt, k, classes="non_empty"):
    """The release's metric, transcribed class by class in float64 (HASSC ssc_metric_torch.py's
    get_score_semantic_and_completion with the mask label != 255, then hassc_voxformer_head.py's
    tp / (tp + fp + fn + 1e-5) and iou[1:].mean()): ``pred``, ``gt`` flat integer sequences of the voxels compared."""
    ious = []
    for j in range(k):
        tp = sum(1 for p, y in zip(pred, gt) if y != 255 and p == j and y == j)
        fp = sum(1 for p, y in zip(pred, gt) if y != 255 and p == j and y != j)
        fn = sum(1 for p, y in zip(pred, gt) if y != 255 and p != j and y == j)
        ious.append(tp / (tp + fp + fn + 1e-5))
    kept = ious[1:] if classes == "non_empty" else ious
    return sum(kept) / len(kept)


def test_the_teacher_miou_is_the_releases_per_sample_metric_over_non_empty_classes() -> None:
    """One sample per GPU in the release: each sample's own mIoU over classes 1..K-1, a class absent from both the
    prediction and the label IoU 0 (0 / 1e-5); ``classes: all`` and ``per: batch`` the other forms."""
    logits = torch.zeros(2, 4, 6, dtype=D)
    preds = [[0, 1, 1, 2, 2, 2], [0, 0, 1, 3, 3, 2]]
    gts = [[0, 1, 2, 2, 2, 255], [1, 0, 1, 3, 255, 0]]  # sample 0: class 3 neither predicted nor labelled
    for b, pred in enumerate(preds):
        logits[b, pred, torch.arange(6)] = 1.0
    gt = torch.tensor(gts)
    got = L.teacher_batch_miou(logits, gt)
    assert got.shape == (2,) and got.dtype == D
    for b in range(2):
        assert float(got[b]) == pytest.approx(release_miou(preds[b], gts[b], 4), rel=1e-12)
    # sample 0 by hand: class 1: 1/2, class 2: 2/3, class 3 absent: 0 (up to the 1e-5 of the denominators)
    assert float(got[0]) == pytest.approx((0.5 + 2 / 3 + 0) / 3, rel=1e-4)
    assert float(L.teacher_batch_miou(logits, gt, classes="all")[0]) == pytest.approx(
        release_miou(preds[0], gts[0], 4, "all"), rel=1e-12)
    pooled = L.teacher_batch_miou(logits, gt, classes="all", per="batch")
    assert pooled.dim() == 0 and float(pooled) == pytest.approx(release_miou(sum(preds, []), sum(gts, []), 4, "all"),
                                                                 rel=1e-12)
    with pytest.raises(ValueError, match="classes must be non_empty or all"):
        L.teacher_batch_miou(logits, gt, classes="some")


def test_hassc_kd_objective_weighs_each_sample_by_its_own_teacher_miou() -> None:
    """The objective's default against the release's per-GPU computation at B = 2: mean_b exp(iou_b[1:].mean()) KL_b
    (DDP's mean over two GPUs of one sample each), every part transcribed in float64."""
    from distilkit.objectives.hassc import HASSCKD, HASSCKDParams

    g = torch.Generator().manual_seed(7)
    k, spatial = 5, (4, 3, 2)
    s, t = rand(2, k, *spatial, g=g), rand(2, k, *spatial, g=g, grad=False)
    lab = labels_of(2, spatial, g, k=k)
    lab[0][lab[0] == 4] = 0  # sample 0: class 4 only where the teacher may predict it
    per_sample = []
    for b in range(2):
        pred, gt = t[b].argmax(0).flatten().tolist(), lab[b].flatten().tolist()
        per_sample.append(release_miou(pred, gt, k))
    want = naive_hassc(s, t, lab, 1.0, per_sample)
    term = HASSCKD(HASSCKDParams())
    got = term.compute({"student": s, "teacher": t, "target": lab}, None)
    assert got.item() == pytest.approx(want.item(), rel=1e-10)
    gs, = torch.autograd.grad(got, s)
    gw, = torch.autograd.grad(want, s)
    assert torch.allclose(gs, gw, rtol=1e-9, atol=1e-12)
    # the pooled, all-class weight of distilkit before v2 differs on this case
    old = HASSCKD(HASSCKDParams(classes="all", per="batch")).compute({"student": s, "teacher": t, "target": lab}, None)
    pooled = release_miou(sum([t[b].argmax(0).flatten().tolist() for b in range(2)], []), lab.flatten().tolist(), k,
                          "all")
    assert old.item() == pytest.approx(naive_hassc(s, t, lab, 1.0, pooled).item(), rel=1e-10)
    assert abs(old.item() - got.item()) > 1e-6


def naive_pad(s, t, labels, include_empty):
    total = 0.0
    for i in range(s.shape[0]):
        terms = []
        for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
            idx = tuple(idx)
            lab = int(labels[(i, *idx)])
            if lab == 255 or (lab == 0 and not include_empty):
                continue
            ls = torch.log_softmax(s[(i, slice(None), *idx)], 0)
            pt = torch.softmax(t[(i, slice(None), *idx)], 0)
            terms += [pt[k] * (torch.log(pt[k]) - ls[k]) for k in range(len(pt))]  # KLDivLoss's pointwise term
        total = total + (sum(terms) / len(terms) if terms else 0.0)
    return total / s.shape[0]


@pytest.mark.parametrize("include_empty", [False, True])
@pytest.mark.filterwarnings("ignore:reduction. 'mean' divides:UserWarning")  # the release's reduction, on purpose
def test_l2cocc_pad_is_kldivloss_mean_over_valid_nonempty_voxels_and_classes(include_empty, device) -> None:
    g = torch.Generator().manual_seed(1)
    s, t = rand(2, 5, 3, 3, 2, g=g), rand(2, 5, 3, 3, 2, g=g)
    lab = labels_of(2, (3, 3, 2), g, k=5)
    on_device_matches(lambda s, t, lab: L.l2cocc_pad(s, t, lab, include_empty),
                      lambda s, t, lab: naive_pad(s, t, lab, include_empty), (s, t, lab), device, rel=1e-9)
    # the release's own computation (torch.nn.KLDivLoss) on one sample
    one = lab[:1]
    keep = (one != 255) & ((one != 0) | include_empty)
    ls = torch.log_softmax(s[:1], 1).permute(0, 2, 3, 4, 1)[keep]
    pt = torch.softmax(t[:1], 1).permute(0, 2, 3, 4, 1)[keep]
    want = torch.nn.KLDivLoss(reduction="mean")(ls[None], pt[None])
    assert L.l2cocc_pad(s[:1], t[:1], one, include_empty).item() == pytest.approx(want.item(), rel=1e-12)
    assert L.l2cocc_pad(s, t, torch.full_like(lab, 255)).item() == 0.0  # nothing to align: 0, not NaN


def naive_fsd(s, t, mask, per_sample=True):
    """1 - cos at each masked position, position by position: each sample's mean, then the mean over the samples
    (a sample without a position: 0), or (``per_sample=False``) the mean over the batch's positions pooled."""
    per, pooled = [], []
    for i in range(s.shape[0]):
        terms = []
        for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
            idx = tuple(idx)
            if not bool(mask[(i, *idx)]):
                continue
            a, b = s[(i, slice(None), *idx)], t[(i, slice(None), *idx)]
            terms.append(1 - (a @ b) / (a.norm() * b.norm()))
        per.append(sum(terms) / len(terms) if terms else torch.zeros((), dtype=D))
        pooled += terms
    if per_sample:
        return sum(per) / len(per)
    return sum(pooled) / len(pooled) if pooled else torch.zeros((), dtype=D)


@pytest.mark.parametrize("spatial", [(4, 3), (3, 2, 2)])
@pytest.mark.parametrize("reduce", ["per_sample", "pooled"])
def test_l2cocc_fsd_is_the_mean_cosine_distance_over_the_masked_positions(spatial, reduce, device) -> None:
    g = torch.Generator().manual_seed(2)
    s, t = rand(2, 6, *spatial, g=g), rand(2, 6, *spatial, g=g)
    mask = torch.rand(2, *spatial, generator=g) < 0.6
    mask[1].view(-1)[:-1] = False  # sample 1: one position, so that the two reductions differ
    on_device_matches(lambda s, t, m: L.l2cocc_fsd(s, t, m, reduce),
                      lambda s, t, m: naive_fsd(s, t, m, reduce == "per_sample"), (s, t, mask), device, rel=1e-9)
    assert L.l2cocc_fsd(s, t, torch.zeros_like(mask), reduce).item() == 0.0
    x, y = rand(2, 3, *spatial, g=g), rand(2, 3, *spatial, g=g, grad=False)
    assert torch.autograd.gradcheck(lambda x: L.l2cocc_fsd(x, y, mask, reduce), (x,))
    with pytest.raises(ValueError, match="per_sample or pooled"):
        L.l2cocc_fsd(s, t, mask, "sum")


def release_fsd(students, teachers, target):
    """L2COcc's CameraSegmentor.distill_loss_feature (numeric part, cos sim) transcribed in float64 for its own
    batch: target 255 -> 0; a 2-D (X, Y) map's mask mean over Z != 0, a 3-D map's target != 0; per map the
    (1 - cos) mean over the masked positions of the batch; the sum over the maps / their number, x 4."""
    target = target.double().masked_fill(target == 255, 0)
    total = 0.0
    for s, t in zip(students, teachers):
        mask = target.mean(3) != 0 if s.dim() == 4 else target != 0
        terms = []
        for i in range(s.shape[0]):
            for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
                if bool(mask[(i, *idx)]):
                    a, b = s[(i, slice(None), *idx)], t[(i, slice(None), *idx)]
                    terms.append(1 - (a @ b) / (a.norm() * b.norm()))
        total = total + sum(terms) / len(terms)
    return total / len(students) * 4


def test_l2cocc_fsd_over_two_maps_is_the_releases_mean_over_its_maps() -> None:
    """One term over a 2-D plane and a 3-D volume (taps student/teacher, student_2/teacher_2) at its weight 4: the
    release's value for one sample (0.2 per map at 20 maps, 2 per map here), and at B = 2 the mean of the per-sample
    release values (one sample per GPU, DDP) or, ``reduce: pooled``, the release's code run on the batch."""
    from distilkit.errors import TapError
    from distilkit.objectives.l2cocc import FSD, FSDParams

    g = torch.Generator().manual_seed(11)
    spatial = (4, 3, 2)
    s2, t2 = rand(2, 5, *spatial[:2], g=g), rand(2, 5, *spatial[:2], g=g, grad=False)
    s3, t3 = rand(2, 3, *spatial, g=g), rand(2, 3, *spatial, g=g, grad=False)
    lab = labels_of(2, spatial, g, k=4)
    lab[1] = 0
    lab[1, 0, 0, 0] = 2  # sample 1: one occupied voxel, so that pooling over the batch differs
    taps = {"student": s2, "teacher": t2, "student_2": s3, "teacher_2": t3, "target": lab}
    weight = FSD.DEFAULT_WEIGHT
    one = weight * FSD(FSDParams()).compute({k: v[:1] for k, v in taps.items()}, None)
    want_one = release_fsd([s2[:1], s3[:1]], [t2[:1], t3[:1]], lab[:1])
    assert one.item() == pytest.approx(want_one.item(), rel=1e-10)
    per_sample = weight * FSD(FSDParams()).compute(taps, None)
    want = sum(release_fsd([s2[i:i + 1], s3[i:i + 1]], [t2[i:i + 1], t3[i:i + 1]], lab[i:i + 1]) for i in range(2)) / 2
    assert per_sample.item() == pytest.approx(want.item(), rel=1e-10)
    ga = torch.autograd.grad(per_sample, (s2, s3))
    gb = torch.autograd.grad(want, (s2, s3))
    assert all(torch.allclose(x, y, rtol=1e-9, atol=1e-12) for x, y in zip(ga, gb))
    pooled = weight * FSD(FSDParams(reduce="pooled")).compute(taps, None)
    assert pooled.item() == pytest.approx(release_fsd([s2, s3], [t2, t3], lab).item(), rel=1e-10)
    assert abs(pooled.item() - per_sample.item()) > 1e-6
    # two terms of one map each at x4 (distilkit's advice before v2) give twice the release's value
    separate = sum(weight * FSD(FSDParams()).compute({"student": s, "teacher": t, "target": lab[:1]}, None)
                   for s, t in ((s2[:1], t2[:1]), (s3[:1], t3[:1])))
    assert separate.item() == pytest.approx(2 * want_one.item(), rel=1e-10)
    with pytest.raises(TapError, match="student_2 is given without teacher_2"):
        FSD(FSDParams()).compute({"student": s2, "teacher": t2, "student_2": s3, "target": lab}, None)


def naive_relation(s, t):
    """The release's form: F.normalize over channels, the dense (B, P, P) cosine matrices, F.l1_loss."""
    a = torch.nn.functional.normalize(s.flatten(2), dim=1)
    b = torch.nn.functional.normalize(t.flatten(2), dim=1)
    cs, ct = a.transpose(1, 2) @ a, b.transpose(1, 2) @ b
    diff = cs - ct
    eye = torch.eye(diff.shape[1], dtype=torch.bool)
    # the diagonal is |1 - 1| = 0 for non-zero rows whatever the features: detached, so that autograd does not take
    # the sign of a rounding residue there (the fast form's convention, see distilkit.losses.l2cocc)
    both = (a.abs().sum(1) > 0) & (b.abs().sum(1) > 0)
    diff = torch.where(eye & both[:, :, None], diff.detach() * 0, diff)
    return diff.abs().mean()


@pytest.mark.parametrize("cs,ct,spatial,entries", [(3, 3, (4, 3), 1 << 24), (4, 6, (3, 3, 2), 7), (2, 5, (5,), 1)])
def test_l2cocc_relation_in_row_blocks_equals_the_dense_pxp_form(cs, ct, spatial, entries, device, monkeypatch) -> None:
    monkeypatch.setattr(l2, "_ENTRIES", entries)  # row blocks of 1, a few, or all rows
    g = torch.Generator().manual_seed(3)
    s, t = rand(2, cs, *spatial, g=g), rand(2, ct, *spatial, g=g)
    with torch.no_grad():
        s[0, :, 0] = 0  # a zero feature: its cosines are 0, its diagonal |0 - 1| = 1
    on_device_matches(L.l2cocc_relation, naive_relation, (s, t), device, rel=1e-9)
    # finite differences (away from the zero feature, where normalising is not continuous)
    x, y = rand(1, cs, *spatial, g=g), rand(1, ct, *spatial, g=g)
    assert torch.autograd.gradcheck(L.l2cocc_relation, (x, y))
    with pytest.raises(ValueError, match="same B and spatial size"):
        L.l2cocc_relation(s, t[..., :1])


@pytest.mark.parametrize("p,entries", [(1, 1), (7, 9), (9, 9), (14, 9), (20, 36), (1600, 1 << 24), (2500, 1 << 20)])
def test_l2cocc_relation_tiles_i_le_j_cover_the_pxp_matrix_once(p, entries, monkeypatch) -> None:
    """The tiles I <= J, those off the diagonal weighted 2, count every entry of the symmetric P x P matrix once;
    each tile within _ENTRIES, the last one ragged where the edge does not divide P."""
    monkeypatch.setattr(l2, "_ENTRIES", entries)
    for where, edge in (("cpu", l2._CPU_TILE), ("cuda", p)):  # the CPU's tiles at most _CPU_TILE wide
        cover = torch.zeros(p, p)
        for i0, i1, j0, j1, weight in l2._RelationL1._tiles(p, torch.device(where)):
            assert i0 <= j0 and (i1 - i0) * (j1 - j0) <= entries and max(i1 - i0, j1 - j0) <= edge
            assert weight == (1.0 if i0 == j0 else 2.0)
            cover[i0:i1, j0:j1] += weight / 2
            cover[j0:j1, i0:i1] += weight / 2
        assert torch.equal(cover, torch.ones(p, p))


def test_l2cocc_relation_tile_is_one_gemm_of_a_minus_b_with_the_zero_diagonal_rule() -> None:
    """A tile of D = a a^T - b b^T from [a | b] [a | -b]^T: off the diagonal, the dense difference's block (its
    diagonal entries not zeroed); on a diagonal tile, D_ii = 0 exactly where a_i and b_i are both non-zero, -1 where
    only a_i is zero, 1 where only b_i is, 0 where both are."""
    g = torch.Generator().manual_seed(5)
    a = torch.nn.functional.normalize(torch.randn(10, 3, dtype=D, generator=g), dim=1)
    b = torch.nn.functional.normalize(torch.randn(10, 4, dtype=D, generator=g), dim=1)
    a[1], b[2], a[3], b[3] = 0, 0, 0, 0
    lhs, rhs, both = l2._RelationL1._operands(a, b)
    dense = a @ a.T - b @ b.T
    buffer = torch.empty(25, dtype=D)
    off = l2._RelationL1._tile(lhs, rhs, both, 0, 5, 5, 10, buffer).clone()
    assert torch.allclose(off, dense[:5, 5:], rtol=0, atol=1e-15)
    assert bool((off.diagonal()[[0, 1, 2, 4]].abs() > 1e-3).all())  # row 3 is zero in both
    diagonal = l2._RelationL1._tile(lhs, rhs, both, 0, 5, 0, 5, buffer).diagonal()
    assert diagonal.tolist() == [0.0, pytest.approx(-1, abs=1e-15), pytest.approx(1, abs=1e-15), 0.0, 0.0]
    assert torch.allclose(l2._RelationL1._tile(lhs, rhs, both, 0, 5, 0, 5, buffer).fill_diagonal_(0),
                          dense[:5, :5].fill_diagonal_(0), rtol=0, atol=1e-15)


@pytest.mark.parametrize("grads", ["student", "teacher", "both"])
def test_l2cocc_relation_over_several_tiles_equals_the_dense_form(grads, device, monkeypatch) -> None:
    """P = 20 in tiles of 6 (I < J tiles, diagonal tiles, a ragged last one of 2 rows), a batch of 3, rows that are
    zero in the student, in the teacher or in both (in a middle and in the ragged tile): value and the gradients
    wanted (the student's, the teacher's or both, in one GEMM) against the dense float64 form."""
    monkeypatch.setattr(l2, "_ENTRIES", 36)
    g = torch.Generator().manual_seed(7)
    s, t = rand(3, 3, 4, 5, g=g, grad=grads != "teacher"), rand(3, 5, 4, 5, g=g, grad=grads != "student")
    with torch.no_grad():
        s[0, :, 1, 2] = 0  # position 7: a zero student row, its diagonal |0 - 1| = 1
        t[1, :, 3, 4] = 0  # position 19, in the ragged tile: a zero teacher row
        s[2, :, 2, 3], t[2, :, 2, 3] = 0, 0  # position 13: zero in both, D's row and column 0
        s[2, :, 0, 0] = 0
    on_device_matches(L.l2cocc_relation, naive_relation, (s, t), device, rel=1e-9)
    one_by_one = torch.stack([naive_relation(s[i:i + 1], t[i:i + 1]) for i in range(3)]).mean()
    assert L.l2cocc_relation(s, t).item() == pytest.approx(one_by_one.item(), rel=1e-12)  # the per-sample mean


def test_l2cocc_relation_gradcheck_over_several_tiles(monkeypatch) -> None:
    """The tiled backward against finite differences, both inputs, a batch of 2, P = 20 in tiles of 6."""
    monkeypatch.setattr(l2, "_ENTRIES", 36)
    g = torch.Generator().manual_seed(11)
    x, y = rand(2, 3, 4, 5, g=g), rand(2, 5, 4, 5, g=g)
    assert torch.autograd.gradcheck(L.l2cocc_relation, (x, y))


def test_l2cocc_relation_in_float32_is_float64s_within_1e6_value_1e5_gradient() -> None:
    """At P = 1,600 in the default tiles (edge 1,024 on the CPU: 3 tiles, the last one 576 rows), float32 inputs
    give float64's value within 1e-6 relative and its gradient within 1e-5 in norm (measured: 2e-8 and 1e-6; the
    dense float32 form: 4e-8 and 1.3e-6)."""
    g = torch.Generator().manual_seed(0)
    s, t = rand(2, 16, 40, 40, g=g), rand(2, 32, 40, 40, g=g, grad=False)
    s32 = s.detach().float().requires_grad_(True)
    want, got = L.l2cocc_relation(s, t), L.l2cocc_relation(s32, t.float())
    assert got.dtype == torch.float32 and got.item() == pytest.approx(want.item(), rel=1e-6)
    (g64,), (g32,) = torch.autograd.grad(want, s), torch.autograd.grad(got, s32)
    assert g32.dtype == torch.float32 and ((g32.double() - g64).norm() / g64.norm()).item() < 1e-5


def test_the_per_sample_kl_and_cosine_sums_compute_only_the_kept_positions() -> None:
    """kl_per_sample and cosine_distance_sums gather the kept positions first: their gradients check, a position
    left out cannot reach the value (a NaN there stays out) and gets a zero gradient."""
    from distilkit.losses.logit import kl_per_sample
    g = torch.Generator().manual_seed(5)
    s, t = rand(3, 4, 3, 2, g=g), rand(3, 4, 3, 2, g=g)
    keep = torch.rand(3, 3, 2, generator=g) < 0.5
    keep[0], keep[1, 0, 0] = False, True  # sample 0 keeps nothing, sample 1 at least one
    assert torch.autograd.gradcheck(lambda s, t: kl_per_sample(s, t, keep, 1.7), (s, t))
    assert torch.autograd.gradcheck(lambda s, t: l2.cosine_distance_sums(s, t, keep)[0], (s, t))
    want = [naive_kl_of_sample(s, t, torch.where(keep, 0, 255), 1.0, i) for i in range(3)]
    poisoned = s.detach().clone()
    poisoned[:, :, ~keep.any(0)] = float("nan")  # positions that no sample keeps
    poisoned[0] = float("nan")  # every position of the sample that keeps none
    got = kl_per_sample(poisoned.requires_grad_(), t, keep)
    assert torch.allclose(got, torch.stack(want).detach(), rtol=1e-9, atol=0)
    sums, counts = l2.cosine_distance_sums(poisoned, t, keep)
    assert torch.isfinite(sums).all() and counts.tolist() == keep.flatten(1).sum(1).tolist() and sums[0] == 0
    got.sum().backward()
    assert (poisoned.grad.permute(0, 2, 3, 1)[~keep] == 0).all()
