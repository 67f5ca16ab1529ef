"""MonoOcc's terms against float64 transcriptions of its release (ucaszyp/MonoOcc at 80a9247,
``projects/mmdet3d_plugin/MonoOcc/utils/ssc_loss.py`` ``Distill_loss`` and ``cos_similarity_2d``), written here from
the release's code — one sample at a time as it runs (``squeeze``, boolean indexing, ``nn.KLDivLoss(log_target=True)``,
``nn.CosineSimilarity``) — not from distilkit's: values and gradients, masks empty and full."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from distilkit.losses.monoocc import monoocc_image, monoocc_kl

D = torch.float64
pytestmark = pytest.mark.filterwarnings("ignore:reduction. 'mean' divides")  # the release's KLDivLoss("mean")


def _release_distill(s, t, target, softmax=False):
    """Distill_loss for one sample (its batch of 1): mask = target not 255 nor 0, [C, N] of both, KLDivLoss(mean,
    log_target=True)(student, teacher); ``softmax``: the divergence of the channels' distributions (log_softmax of
    both first), the form distilkit defaults to."""
    valid = (target != 255) & (target != 0)
    bs, bt = s.squeeze(0)[:, valid].unsqueeze(0), t.squeeze(0)[:, valid].unsqueeze(0)
    if softmax:
        bs, bt = F.log_softmax(bs, dim=1), F.log_softmax(bt, dim=1)
    return nn.KLDivLoss(reduction="mean", log_target=True)(bs, bt)


def _release_image(s, t):
    """cos_similarity_2d without its ratio: the teacher resized (bilinear, corners aligned), pixels as rows,
    1 - mean cosine over the channels."""
    _, c, h, w = s.shape
    t = F.interpolate(t, size=(h, w), mode="bilinear", align_corners=True)
    rows_s = s.permute(0, 2, 3, 1).reshape(-1, c)
    rows_t = t.permute(0, 2, 3, 1).reshape(-1, c)
    return 1 - nn.CosineSimilarity(dim=1)(rows_s, rows_t).mean()


@pytest.mark.parametrize("shape", [(1, 6, 4, 4, 2), (2, 8, 3, 4, 2), (3, 4, 2, 2, 2)])
@pytest.mark.parametrize("form", ["raw", "softmax"])
def test_voxel_term_is_the_release_per_sample(shape, form):
    g = torch.Generator().manual_seed(sum(shape))
    s = torch.randn(shape, generator=g, dtype=D, requires_grad=True)
    t = torch.randn(shape, generator=g, dtype=D)
    target = torch.randint(0, 4, shape[:1] + shape[2:], generator=g)
    target[torch.rand(target.shape, generator=g) < 0.15] = 255
    target[:, 0, 0, 0] = 1
    ours = monoocc_kl(s, t, (target != 0) & (target != 255), form)
    theirs = sum(_release_distill(s[i:i + 1], t[i:i + 1], target[i], form == "softmax")
                 for i in range(shape[0])) / shape[0]
    assert torch.allclose(ours, theirs, rtol=1e-12)
    (g_ours,) = torch.autograd.grad(ours, s)
    (g_theirs,) = torch.autograd.grad(theirs, s)
    assert torch.allclose(g_ours, g_theirs, rtol=1e-10, atol=1e-15)
    mask = (target != 0) & (target != 255)
    assert torch.autograd.gradcheck(lambda x: monoocc_kl(x, t, mask, form), (s,))


def test_the_release_form_is_linear_in_the_student_and_has_no_minimum_at_the_teacher():
    t = torch.randn(1, 5, 2, 2, 2, dtype=D)
    mask = torch.ones(1, 2, 2, 2, dtype=torch.bool)
    at_teacher = monoocc_kl(t.clone(), t, mask, "raw")
    assert torch.allclose(at_teacher, torch.zeros((), dtype=D))
    assert monoocc_kl(t + 1, t, mask, "raw") < at_teacher  # larger student features: a lower value, no minimum
    s = torch.randn(1, 5, 2, 2, 2, dtype=D, requires_grad=True)
    (grad,) = torch.autograd.grad(monoocc_kl(s, t, mask, "raw"), s)
    assert torch.allclose(grad, -t.exp() / (5 * 8))  # -exp(t) / (C n): whatever the student is
    assert monoocc_kl(t.clone(), t, mask, "softmax").abs() < 1e-15  # the divergence: 0 at the teacher
    assert monoocc_kl(t + torch.randn_like(t), t, mask, "softmax") > 0


def test_voxel_term_masks_empty_and_full():
    s, t = torch.randn(2, 3, 2, 2, 2, dtype=D), torch.randn(2, 3, 2, 2, 2, dtype=D)
    full = torch.ones(2, 2, 2, 2, dtype=torch.long)
    assert torch.allclose(monoocc_kl(s, t, full.bool(), "raw"),
                          (_release_distill(s[:1], t[:1], full[0]) + _release_distill(s[1:], t[1:], full[1])) / 2)
    empty = full.clone()
    empty[1] = 0
    assert torch.isnan(_release_distill(s[1:], t[1:], empty[1]))  # the release: NaN; here the sample gives 0
    assert torch.allclose(monoocc_kl(s, t, empty.bool(), "raw"), _release_distill(s[:1], t[:1], full[0]) / 2)
    with pytest.raises(ValueError, match="form must be"):
        monoocc_kl(s, t, full.bool(), "kl")


@pytest.mark.parametrize("sizes", [((6, 8), (3, 4)), ((5, 7), (5, 7)), ((4, 4), (7, 3))])
def test_image_term_is_the_release(sizes):
    (h, w), (th, tw) = sizes
    g = torch.Generator().manual_seed(h * w)
    s = torch.randn(2, 6, h, w, generator=g, dtype=D, requires_grad=True)
    t = torch.randn(2, 6, th, tw, generator=g, dtype=D)
    ours, theirs = monoocc_image(s, t), _release_image(s, t)
    assert torch.allclose(ours, theirs, rtol=1e-12)
    (g_ours,) = torch.autograd.grad(ours, s)
    (g_theirs,) = torch.autograd.grad(theirs, s)
    assert torch.allclose(g_ours, g_theirs, rtol=1e-10, atol=1e-15)
    with pytest.raises(ValueError, match="connector"):
        monoocc_image(s, torch.randn(2, 5, th, tw, dtype=D))
