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


def naive_hassc(s, t, labels, temp, miou):
    total, samples = 0.0, 0
    for i in range(s.shape[0]):
        vals = []
        for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
            idx = tuple(idx) if isinstance(idx, list) else (idx,)
            if int(labels[(i, *idx)]) == 255:
                continue
            zs, zt = s[(i, slice(None), *idx)] / temp, t[(i, slice(None), *idx)] / temp
            ps, pt = torch.softmax(zs, 0), torch.softmax(zt, 0)
            vals.append(sum(pt[k] * (torch.log(pt[k]) - torch.log(ps[k])) for k in range(len(pt))) * temp ** 2)
        total = total + (sum(vals) / len(vals) if vals else 0.0)
        samples += 1
    out = total / samples
    return out * math.exp(miou) if miou is not None else out


@pytest.mark.parametrize("temp,miou", [(1.0, None), (2.5, 0.3)])
def test_hassc_kd_is_the_per_sample_mean_of_the_valid_voxels_kl(temp, miou, device) -> None:
    g = torch.Generator().manual_seed(0)
    s, t = rand(2, 4, 3, 2, 2, g=g), rand(2, 4, 3, 2, 2, g=g)
    lab = labels_of(2, (3, 2, 2), g)
    on_device_matches(lambda s, t, lab: L.hassc_kd(s, t, lab, temp, miou),
                      lambda s, t, lab: naive_hassc(s, t, lab, temp, miou), (s, t, lab), device, rel=1e-9)
    lab[1] = 255  # a sample without a valid voxel gives 0 and still counts in the batch mean
    assert math.isclose(L.hassc_kd(s, t, lab, temp).item(), naive_hassc(s, t, lab, temp, None).item(), rel_tol=1e-9)
    with pytest.raises(ValueError, match="labels"):
        L.hassc_kd(s, t, lab[:, :1])


def test_the_teacher_miou_counts_an_absent_class_as_zero() -> None:
    logits = torch.zeros(1, 4, 6)
    pred = torch.tensor([0, 1, 1, 2, 2, 2])  # class 3 neither predicted nor labelled
    logits[0, pred, torch.arange(6)] = 1.0
    gt = torch.tensor([[0, 1, 2, 2, 2, 255]])
    # class 0: 1/1; class 1: 1/2 (predicted twice, labelled once); class 2: 2/3 (the ignored voxel left out)
    assert float(L.teacher_batch_miou(logits, gt)) == pytest.approx((1 + 0.5 + 2 / 3 + 0) / 4)


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


def naive_fsd(s, t, mask):
    terms = []
    for i in range(s.shape[0]):
        for idx in torch.cartesian_prod(*[torch.arange(n) for n in s.shape[2:]]).tolist():
            idx = tuple(idx)
            if not bool(mask[(i, *idx)]):
                continue
            a, b = s[(i, slice(None), *idx)], t[(i, slice(None), *idx)]
            terms.append(1 - (a @ b) / (a.norm() * b.norm()))
    return sum(terms) / len(terms)


@pytest.mark.parametrize("spatial", [(4, 3), (3, 2, 2)])
def test_l2cocc_fsd_is_the_mean_cosine_distance_over_the_masked_positions(spatial, device) -> None:
    g = torch.Generator().manual_seed(2)
    s, t = rand(2, 6, *spatial, g=g), rand(2, 6, *spatial, g=g)
    mask = torch.rand(2, *spatial, generator=g) < 0.6
    on_device_matches(L.l2cocc_fsd, naive_fsd, (s, t, mask), device, rel=1e-9)
    assert L.l2cocc_fsd(s, t, torch.zeros_like(mask)).item() == 0.0


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
