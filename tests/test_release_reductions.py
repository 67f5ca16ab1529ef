"""The batch reductions of HASSC's and L2COcc's terms at B = 2 against float64 transcriptions of their releases run one
sample per GPU (HASSC ``samples_per_gpu=1``, L2COcc ``batch_size=1``; DDP averages the gradients, so the release's
value for a batch is the mean of its per-sample values): ``reduce: per_sample`` (the default) is that mean,
``reduce: pooled`` the release's code run on the whole batch. ``hassc_kd``'s per-sample weight and ``l2cocc_fsd``'s
two maps at B = 2: tests/test_hassc_l2cocc_losses.py; ``hassc_hvm``'s whole objective: tests/test_hassc_hardness.py."""

from __future__ import annotations

import pytest
import torch

from test_hassc_hardness import naive_ce, naive_lga

D = torch.float64


def _labels(g: torch.Generator, b: int, spatial: tuple[int, ...], k: int) -> torch.Tensor:
    lab = torch.randint(0, k, (b, *spatial), generator=g)
    lab[torch.rand(lab.shape, generator=g) < 0.2] = 255
    lab[1][lab[1] != 255] = 0
    lab[1].view(-1)[:2] = torch.tensor([2, 1])  # sample 1: few non-empty voxels, so that pooling weighs it less
    return lab


def release_loss_ssc(logits: torch.Tensor, labels: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """HASSC's head on one sample (hassc_voxformer_head.py, step): CE_ssc_loss (class-weighted, reduction none) at the
    voxels with target != 255, times 1 + LGA, their mean; voxel by voxel."""
    lga = naive_lga(labels[None])[0]
    terms = [weights[int(labels[v])] * naive_ce(logits[(slice(None), *v)], int(labels[v])) * (1 + lga[v])
             for v in map(tuple, (labels != 255).nonzero().tolist())]
    return torch.stack(terms).mean()


@pytest.mark.parametrize("reduce", ["per_sample", "pooled"])
def test_hassc_ce_at_two_samples(reduce: str) -> None:
    from distilkit.losses.task import GeometryWeightedCE, _GeometryCEParams

    g = torch.Generator().manual_seed(21)
    k = 4
    labels = _labels(g, 2, (4, 3, 3), k)
    logits = torch.randn(2, k, 4, 3, 3, dtype=D, generator=g, requires_grad=True)
    weights = torch.tensor([0.4, 0.6, 0.8, 0.7], dtype=D)
    term = GeometryWeightedCE(_GeometryCEParams(reduce=reduce))
    term.weight = weights
    got = term.compute({"student": logits, "target": labels}, None)
    if reduce == "per_sample":
        want = (release_loss_ssc(logits[0], labels[0], weights) + release_loss_ssc(logits[1], labels[1], weights)) / 2
    else:  # the release's code on the batch: the mean over the batch's valid voxels
        lga = naive_lga(labels)
        want = torch.stack([weights[int(labels[v])] * naive_ce(logits[(v[0], slice(None), *v[1:])], int(labels[v]))
                            * (1 + lga[v]) for v in map(tuple, (labels != 255).nonzero().tolist())]).mean()
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(got, logits)[0], torch.autograd.grad(want, logits)[0],
                               rtol=1e-10, atol=1e-14)
    other = GeometryWeightedCE(_GeometryCEParams(reduce="pooled" if reduce == "per_sample" else "per_sample"))
    other.weight = weights
    assert abs(other.compute({"student": logits, "target": labels}, None).item() - got.item()) > 1e-6


def release_hvm(logits: torch.Tensor, labels: torch.Tensor, lga: torch.Tensor, weights: torch.Tensor,
                alpha: float, beta: float) -> torch.Tensor:
    """HASSC's loss_hard_voxel_mining on one sample's (K, N) sampled logits: Σ_valid CE (α + β LGA) / Σ_valid w_y."""
    num, den = torch.zeros((), dtype=D), 0.0
    for i in range(labels.shape[0]):
        y = int(labels[i])
        if y != 255:
            num = num + naive_ce(logits[:, i], y) * (alpha + beta * float(lga[i]))
            den += float(weights[y])
    return num / den


@pytest.mark.parametrize("reduce", ["per_sample", "pooled"])
def test_hard_voxel_ce_at_two_samples(reduce: str) -> None:
    from distilkit.losses.hardness import hard_voxel_ce

    g = torch.Generator().manual_seed(22)
    logits = torch.randn(2, 4, 10, dtype=D, generator=g, requires_grad=True)
    labels = torch.randint(0, 4, (2, 10), generator=g)
    labels[1, 3:] = 255  # sample 1: three valid positions
    lga = torch.randint(0, 7, (2, 10), generator=g).double()
    weights = torch.tensor([0.4, 0.6, 0.8, 0.7], dtype=D)
    got = hard_voxel_ce(logits, labels, lga, weights, 0.2, 1.0, reduce=reduce)
    if reduce == "per_sample":
        want = sum(release_hvm(logits[b], labels[b], lga[b], weights, 0.2, 1.0) for b in range(2)) / 2
    else:  # the release's code on the batch: both sums over the batch
        want = release_hvm(logits.transpose(0, 1).reshape(4, 20), labels.reshape(20), lga.reshape(20), weights, 0.2,
                           1.0)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(got, logits)[0], torch.autograd.grad(want, logits)[0],
                               rtol=1e-10, atol=1e-14)
    assert torch.autograd.gradcheck(lambda z: hard_voxel_ce(z, labels, lga, weights, reduce=reduce), (logits,),
                                    fast_mode=True)
    labels[1] = 255  # a sample without a valid position: 0, counted in the mean (the release: 0 / 0)
    none = hard_voxel_ce(logits, labels, lga, weights, 0.2, 1.0, reduce="per_sample")
    torch.testing.assert_close(none, release_hvm(logits[0], labels[0], lga[0], weights, 0.2, 1.0) / 2)
    with pytest.raises(ValueError, match="per_sample or pooled"):
        hard_voxel_ce(logits, labels, lga, weights, reduce="mean")


@pytest.mark.filterwarnings("ignore:reduction. 'mean' divides:UserWarning")  # the release's reduction, on purpose
def test_l2cocc_pad_at_two_samples_is_the_mean_of_the_releases_per_sample_kldivloss() -> None:
    from distilkit.objectives.l2cocc import PAD, PADParams

    g = torch.Generator().manual_seed(23)
    k = 5
    labels = _labels(g, 2, (3, 3, 2), k)
    s = torch.randn(2, k, 3, 3, 2, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(2, k, 3, 3, 2, dtype=D, generator=g)
    got = PAD(PADParams()).compute({"student": s, "teacher": t, "target": labels}, None)
    per_gpu = []
    for b in range(2):  # CameraSegmentor.distill_loss_logits on one sample: KLDivLoss(reduction="mean") / 1
        keep = (labels[b] != 255) & (labels[b] != 0)
        ls = torch.log_softmax(s[b], 0).permute(1, 2, 3, 0)[keep]
        pt = torch.softmax(t[b], 0).permute(1, 2, 3, 0)[keep]
        per_gpu.append(torch.nn.KLDivLoss(reduction="mean")(ls[None], pt[None]))
    want = sum(per_gpu) / 2
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(got, s)[0], torch.autograd.grad(want, s)[0], rtol=1e-10,
                               atol=1e-14)


def test_l2cocc_relation_at_two_samples_is_the_mean_of_the_releases_per_sample_l1() -> None:
    from distilkit.objectives.l2cocc import NoParams, Relation

    g = torch.Generator().manual_seed(24)
    s = torch.randn(2, 3, 4, 3, dtype=D, generator=g, requires_grad=True)
    t = torch.randn(2, 5, 4, 3, dtype=D, generator=g)
    got = Relation(NoParams()).compute({"student": s, "teacher": t}, None)
    per_gpu = []
    for b in range(2):  # calculate_cosine_similarity of one sample with itself, both models, then F.l1_loss
        a = torch.nn.functional.normalize(s[b:b + 1].flatten(2), dim=1)
        c = torch.nn.functional.normalize(t[b:b + 1].flatten(2), dim=1)
        diff = a.transpose(1, 2) @ a - c.transpose(1, 2) @ c
        eye = torch.eye(diff.shape[1], dtype=torch.bool)[None]
        diff = torch.where(eye, diff.detach() * 0, diff)  # |1 - 1| on the diagonal (see test_hassc_l2cocc_losses)
        per_gpu.append(torch.nn.functional.l1_loss(diff, torch.zeros_like(diff)))
    want = sum(per_gpu) / 2
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0)
    torch.testing.assert_close(torch.autograd.grad(got, s)[0], torch.autograd.grad(want, s)[0], rtol=1e-10,
                               atol=1e-14)
