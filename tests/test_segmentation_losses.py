"""Lovász-softmax and CE against naive implementations (Berman et al. 2018; SCPNet eq. 4)."""

from __future__ import annotations

import pytest
import torch

from distilkit.losses import cross_entropy, lovasz_softmax


def naive_lovasz(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Per-class loop: sort errors, Lovász extension of the Jaccard loss (the paper's Alg. 1)."""
    losses = []
    for c in range(probs.shape[1]):
        fg = (labels == c).double()
        if fg.sum() == 0:
            continue
        err = (fg - probs[:, c]).abs()
        order = torch.argsort(err, descending=True, stable=True)
        e, f = err[order], fg[order]
        p = len(f)
        jac = []
        for i in range(p):
            inter = f.sum() - f[: i + 1].sum()
            union = f.sum() + (1 - f[: i + 1]).sum()
            jac.append(1 - inter / union)
        jac = torch.stack(jac)
        grad = torch.cat([jac[:1], jac[1:] - jac[:-1]])
        losses.append((e * grad).sum())
    return torch.stack(losses).mean()


def test_lovasz_matches_naive_value_and_gradient() -> None:
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 4, 3, 3, 2, dtype=torch.float64, generator=g, requires_grad=True)
    labels = torch.randint(0, 3, (2, 3, 3, 2), generator=g)  # class 3 absent
    labels[1, 0, 0, 0] = 255
    fast = lovasz_softmax(logits, labels)
    probs = logits.softmax(1).movedim(1, -1).reshape(-1, 4)
    flat = labels.reshape(-1)
    keep = flat != 255
    slow = naive_lovasz(probs[keep], flat[keep])
    assert fast.item() == pytest.approx(slow.item(), rel=1e-9)
    g1 = torch.autograd.grad(fast, logits)[0]
    g2 = torch.autograd.grad(slow, logits)[0]
    assert torch.allclose(g1, g2, rtol=1e-6, atol=1e-10)


def test_ce_ignores_255_and_empty_is_zero() -> None:
    logits = torch.randn(1, 3, 2, 2, 1, requires_grad=True)
    labels = torch.tensor([[[[0], [1]], [[255], [2]]]])
    manual = -logits.log_softmax(1)[0, :, :, :, 0]
    want = (manual[0, 0, 0] + manual[1, 0, 1] + manual[2, 1, 1]) / 3
    assert cross_entropy(logits, labels).item() == pytest.approx(want.item(), rel=1e-6)
    assert cross_entropy(logits, torch.full_like(labels, 255)).item() == 0.0
    assert lovasz_softmax(logits, torch.full_like(labels, 255)).item() == 0.0


def test_shape_errors_are_named() -> None:
    with pytest.raises(ValueError, match="logits"):
        cross_entropy(torch.randn(1, 3, 4), torch.zeros(1, 5, dtype=torch.long))
