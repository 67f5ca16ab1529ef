"""ScoreLiDAR's VSD surrogate and structural loss (eq. 9-17) against naive float64 loops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import distilkit.losses as L
from distilkit.geometry.nearest import knn_excluding_self, nearest
from distilkit.taps import PointCloud


def val(x: torch.Tensor) -> float:
    return float(x.detach())


def same_on(device: torch.device, fn, *inputs: torch.Tensor) -> None:
    """``fn`` of ``inputs`` copied to ``device`` against ``fn`` of them here: the value and the gradient of each
    input that requires one (the CPU value itself is checked against the naive form by the test)."""
    here = [x.detach().to(device).requires_grad_(x.requires_grad) for x in inputs]
    a, b = fn(*here), fn(*inputs)
    assert val(a) == pytest.approx(val(b), rel=1e-9, abs=1e-12)
    wants = [i for i, x in enumerate(inputs) if x.requires_grad]
    for x, y in zip(torch.autograd.grad(a, [here[i] for i in wants]), torch.autograd.grad(b, [inputs[i] for i in wants])):
        assert torch.allclose(x.cpu(), y, rtol=1e-9, atol=1e-12)


def cloud(m: int, seed: int, scale: float = 5.0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(m, 3, generator=g, dtype=torch.float64) * scale


def naive_nn(q: np.ndarray, s: np.ndarray) -> np.ndarray:
    d = ((q[:, None, :] - s[None, :, :]) ** 2).sum(-1)
    return d.argmin(1)


def naive_curvature(p: np.ndarray, k: int) -> np.ndarray:
    out = []
    for i in range(len(p)):
        d = np.sqrt(((p - p[i]) ** 2).sum(1))
        d[i] = np.inf
        nbr = p[np.argsort(d, kind="stable")[:k]]
        c = nbr - nbr.mean(0)
        lam = np.linalg.eigvalsh(c.T @ c / k)
        out.append(lam[0] / lam.sum())
    return np.array(out)


def test_nearest_and_self_excluded_neighbours_match_brute_force() -> None:
    q, s = cloud(50, 0), cloud(80, 1)
    assert torch.equal(nearest(q, s), torch.from_numpy(naive_nn(q.numpy(), s.numpy())))
    p = torch.cat([cloud(30, 2), cloud(30, 2)[:3]])  # three points present twice
    nbr = knn_excluding_self(p, 5)
    assert not (nbr == torch.arange(len(p))[:, None]).any()
    for i in range(len(p)):
        d = ((p - p[i]) ** 2).sum(1)
        d[i] = float("inf")
        assert torch.allclose(d[nbr[i]].sort().values, d.sort().values[:5])


def test_scene_wise_is_the_mean_squared_distance_to_the_nearest_target_point(device) -> None:
    g, t = cloud(40, 3).requires_grad_(), cloud(70, 4)
    same_on(device, L.scene_wise, g, t)
    idx = naive_nn(g.detach().numpy(), t.numpy())
    want = ((g.detach().numpy() - t.numpy()[idx]) ** 2).mean()  # per element: the released code's MSE scale
    assert val(L.scene_wise(g, t)) == pytest.approx(want, rel=1e-12)
    assert val(L.scene_wise(g, t, reduction="sum")) == pytest.approx(3 * want, rel=1e-12)  # eq. 12's squared norm
    assert torch.autograd.gradcheck(lambda x: L.scene_wise(x, t), (g,))
    assert torch.autograd.gradcheck(lambda x: L.scene_wise(x, t, reduction="sum"), (g,))
    with pytest.raises(ValueError, match="reduction"):
        L.scene_wise(g, t, reduction="max")
    # the released code: index-aligned MSE per coordinate (seed_code.md §3.5)
    t40 = t[:40]
    assert val(L.scene_wise(g, t40, legacy_index_aligned=True)) == pytest.approx(
        float(((g.detach() - t40) ** 2).mean()), rel=1e-12)
    # a batch is the mean over its scenes
    batch_g = PointCloud.from_list([g.detach(), g.detach()[:25]])
    batch_t = PointCloud.from_list([t, t[:50]])
    want = (L.scene_wise(g.detach(), t) + L.scene_wise(g.detach()[:25], t[:50])) / 2
    assert val(L.scene_wise(batch_g, batch_t)) == pytest.approx(float(want), rel=1e-12)


def test_curvature_follows_eq_13_to_15(device) -> None:
    p = cloud(60, 5)
    assert np.allclose(L.curvature(p.to(device), k=8).cpu().numpy(), naive_curvature(p.numpy(), 8), rtol=1e-9,
                       atol=1e-12)
    plane = torch.cat([cloud(50, 6)[:, :2], torch.zeros(50, 1, dtype=torch.float64)], 1)
    assert L.curvature(plane, k=6).abs().max() < 1e-12  # a plane has no variation out of it


def test_key_points_are_the_most_curved_of_a_random_sample() -> None:
    p = cloud(300, 7)
    got = L.select_keypoints(p, k=10, sample_ratio=0.2, keep_ratio=0.25, generator=torch.Generator().manual_seed(3))
    sample = torch.randperm(300, generator=torch.Generator().manual_seed(3))[:60]
    kappa = naive_curvature(p[sample].numpy(), 10)
    want = sample[torch.from_numpy(np.argsort(-kappa, kind="stable")[:15])]
    assert got.tolist() == want.tolist()


def test_point_wise_compares_distance_matrices_of_key_points_and_their_nearest_generated_points(device) -> None:
    g, t = cloud(45, 8).requires_grad_(), cloud(90, 9)
    key = torch.tensor([3, 17, 40, 41, 88])
    same_on(device, L.point_wise, g, t, key)
    kp = t[key].numpy()
    matched = g.detach().numpy()[naive_nn(kp, g.detach().numpy())]
    d_t = np.sqrt(((kp[:, None] - kp[None]) ** 2).sum(-1))
    d_g = np.sqrt(((matched[:, None] - matched[None]) ** 2).sum(-1))
    assert val(L.point_wise(g, t, key)) == pytest.approx(((d_t - d_g) ** 2).mean(), rel=1e-10)
    assert torch.autograd.gradcheck(lambda x: L.point_wise(x, t, key), (g,))
    total = L.structural(g, t, key)
    assert val(total) == pytest.approx(val(0.5 * L.scene_wise(g, t) + 0.01 * L.point_wise(g, t, key)), rel=1e-12)
    batch = L.point_wise(PointCloud.from_list([g.detach()] * 2), PointCloud.from_list([t, t]), [key, key[:3]])
    want = (L.point_wise(g.detach(), t, key) + L.point_wise(g.detach(), t, key[:3])) / 2
    assert val(batch) == pytest.approx(float(want), rel=1e-12)


def test_vsd_gradient_is_the_formula_and_not_zero_unlike_the_released_form(device) -> None:
    x0 = cloud(30, 10).requires_grad_()
    e_t, e_a = cloud(30, 11), cloud(30, 12)
    w = torch.tensor(0.7, dtype=torch.float64)
    same_on(device, L.vsd, x0, e_t, e_a, w)
    L.vsd(x0, e_t, e_a, w).backward()
    assert torch.allclose(x0.grad, w * (e_t - e_a) / x0.numel(), rtol=0, atol=1e-15)
    assert x0.grad.abs().max() > 0
    # ScoreLiDAR's released loss: ((eps_teacher - eps_aux) * (x_t - x_0)).mean() with x_t = x_0 + sigma eps
    x0.grad = None
    x_t = x0 + 0.3 * cloud(30, 13)
    ((e_t - e_a) * (x_t - x0)).mean().backward()
    assert x0.grad.abs().max() == 0  # exactly zero: the term the paper describes does nothing there
    with pytest.raises(ValueError, match="one shape"):
        L.vsd(x0, e_t[:10], e_a)


def test_distillation_dpo_moves_the_winner_like_vsd_and_the_loser_the_other_way(device) -> None:
    """Distillation-DPO's intended generator gradient (issue 18): exact for both completions, and none reaches the
    four noise predictions (the released loss's gradient is 0, as ScoreLiDAR's)."""
    win, lose = cloud(30, 20).requires_grad_(), cloud(30, 21).requires_grad_()
    preds = [cloud(30, s).requires_grad_() for s in (22, 23, 24, 25)]
    same_on(device, lambda w, l, *p: L.distillation_dpo(w, l, *(x.detach() for x in p), weight=0.5), win, lose,
            *(p.detach() for p in preds))
    e_tw, e_aw, e_tl, e_al = preds
    w = torch.tensor([[[0.5]], [[2.0]]], dtype=torch.float64)  # w(t) per scene
    win2, lose2 = win.expand(2, -1, -1), lose.expand(2, -1, -1)
    loss = L.distillation_dpo(win2, lose2, *(p.expand(2, -1, -1) for p in preds), weight=w)
    loss.backward()
    n = win2.numel()
    assert torch.allclose(win.grad, (w * (e_tw - e_aw)).sum(0) / n, rtol=0, atol=1e-15)
    assert torch.allclose(lose.grad, -(w * (e_tl - e_al)).sum(0) / n, rtol=0, atol=1e-15)
    assert all(p.grad is None for p in preds) and win.grad.abs().max() > 0
    with pytest.raises(ValueError, match="same scans"):
        L.distillation_dpo(win, lose[:10], e_tw, e_aw, e_tl, e_al)


def test_distillation_dpo_keeps_a_number_weight_in_the_inputs_precision() -> None:
    """A weight given as a number (0.3: not a float32 value) reaches a float64 gradient unrounded (issue 33: it was
    made in float32 first, 1.7e-8 relative error where every other objective holds 1e-9)."""
    win, lose = cloud(30, 20).requires_grad_(), cloud(30, 21).requires_grad_()
    e_tw, e_aw, e_tl, e_al = (cloud(30, s) for s in (22, 23, 24, 25))
    L.distillation_dpo(win, lose, e_tw, e_aw, e_tl, e_al, weight=0.3).backward()
    assert torch.allclose(win.grad, 0.3 * (e_tw - e_aw) / win.numel(), rtol=1e-15, atol=0)
    assert torch.allclose(lose.grad, -0.3 * (e_tl - e_al) / win.numel(), rtol=1e-15, atol=0)


def test_distillation_dpo_paper_sign_negates_both_gradients() -> None:
    """Eq. 16-18 as printed push the winner away from the teacher's score: the release's gradient negated."""
    grads = {}
    for sign in ("release", "paper"):
        win, lose = cloud(30, 20).requires_grad_(), cloud(30, 21).requires_grad_()
        L.distillation_dpo(win, lose, *(cloud(30, s) for s in (22, 23, 24, 25)), sign=sign).backward()
        grads[sign] = (win.grad, lose.grad)
    assert torch.equal(grads["paper"][0], -grads["release"][0]) and torch.equal(grads["paper"][1], -grads["release"][1])
    with pytest.raises(ValueError, match="sign"):
        L.distillation_dpo(win, lose, *(cloud(30, s) for s in (22, 23, 24, 25)), sign="other")


@pytest.mark.parametrize("sign", ["release", "paper"])
def test_bounded_distillation_dpo_is_diffusion_dpos_log_sigmoid(sign: str) -> None:
    """beta: (2 / beta) softplus(-beta s Delta) per scene, Delta = r_w - r_l with r = mean w [(eps - eps_aux)^2 -
    (eps - eps_teacher)^2]; each scene's linear gradient times 2 sigmoid(-beta s Delta) (naive, float64, per scene)."""
    b, m, beta = 3, 20, 40.0
    g = torch.Generator().manual_seed(7)
    rand = lambda: torch.randn(b, m, 3, generator=g, dtype=torch.float64)  # noqa: E731
    win, lose = rand().requires_grad_(), rand().requires_grad_()
    e_tw, e_aw, e_tl, e_al, noise_w, noise_l = (rand() for _ in range(6))
    e_aw = e_aw * 0.3 + noise_w * 0.7  # margins of both signs and several sizes
    w = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    loss = L.distillation_dpo(win, lose, e_tw, e_aw, e_tl, e_al, weight=w[:, None, None], sign=sign, beta=beta,
                              noise_w=noise_w, noise_l=noise_l)
    loss.backward()
    s = 1.0 if sign == "release" else -1.0
    n = win.numel()
    value = 0.0
    for i in range(b):
        def reward(eps, e_t, e_a):
            return sum(float(w[i]) * (float(eps[i, j, k] - e_a[i, j, k]) ** 2 - float(eps[i, j, k] - e_t[i, j, k]) ** 2)
                       for j in range(m) for k in range(3)) / (m * 3)
        margin = s * (reward(noise_w, e_tw, e_aw) - reward(noise_l, e_tl, e_al))
        value += 2.0 / beta * math.log1p(math.exp(-beta * margin)) / b
        factor = 2.0 / (1.0 + math.exp(beta * margin))
        assert torch.allclose(win.grad[i], factor * s * w[i] * (e_tw[i] - e_aw[i]) / n, rtol=1e-12, atol=1e-18)
        assert torch.allclose(lose.grad[i], -factor * s * w[i] * (e_tl[i] - e_al[i]) / n, rtol=1e-12, atol=1e-18)
    assert float(loss.detach()) == pytest.approx(value, rel=1e-12)
    # at a zero margin the bounded gradient is the linear one; far ahead, it vanishes
    win0 = rand().requires_grad_()
    L.distillation_dpo(win0, lose.detach(), e_tw, e_aw, e_tw, e_aw, beta=beta, noise_w=noise_w).backward()
    lin = win0.detach().clone().requires_grad_()
    L.distillation_dpo(lin, lose.detach(), e_tw, e_aw, e_tw, e_aw).backward()
    assert torch.allclose(win0.grad, lin.grad, rtol=1e-12)
    with pytest.raises(ValueError, match="noise_w"):
        L.distillation_dpo(win, lose, e_tw, e_aw, e_tl, e_al, beta=beta)
