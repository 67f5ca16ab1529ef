"""The deterministic forms of what PyTorch flags on CUDA under ``torch.use_deterministic_algorithms``, against the
forms they replace and naive float64 references (computed on the device of ``--device``, references on the CPU):

* class-weighted cross entropy (``nll_loss2d``'s reduced forms): :func:`distilkit.losses.weighted_cross_entropy`;
* PVKD's difficulty-aware draw (``index_reduce_``): :func:`distilkit.objectives.relational.supervoxel_draw_weight`;
* the Lovász-softmax's running counts (floating-point ``cumsum``): integer sums in :func:`lovasz_softmax`;
* HASSC's reads at sampled positions (``grid_sample``'s backward): ``gather`` in :func:`voxel_sample`;
* the depth loss's resize (bilinear ``interpolate``'s backward): two matrix products in :func:`resize_bilinear`.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import pytest
import torch
import torch.nn.functional as F

import distilkit.losses as L
from distilkit.losses import weighted_cross_entropy
from distilkit.losses.proposal import resize_bilinear
from distilkit.objectives.relational import supervoxel_draw_weight

D = torch.float64
IGNORE = 255
# the earlier PVKD draw, run here as the reference, warns that index_reduce is in beta
INDEX_REDUCE_BETA = pytest.mark.filterwarnings(r"ignore:index_reduce\(\) is in beta")
SHAPES = {"2d": (11, 4), "4d": (2, 4, 3, 5), "5d": (2, 4, 3, 2, 3)}


@contextlib.contextmanager
def strict_determinism() -> Iterator[None]:
    """``torch.use_deterministic_algorithms(True)``, errors and not warnings, the process's setting restored after."""
    was = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(was[0], warn_only=was[1])


def naive_ce(logits: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None, ignore_index: int,
             reduction: str) -> torch.Tensor:
    """Σ_i w_{y_i} (log Σ_c exp z_ic − z_{i y_i}) over the positions not ignored, per position / summed / divided by
    Σ_i w_{y_i}: no log_softmax, no nll_loss."""
    k = logits.shape[1]
    z = logits.movedim(1, -1).reshape(-1, k)
    y = target.reshape(-1)
    rows = []
    weights = []
    for i in range(z.shape[0]):
        if int(y[i]) == ignore_index:
            rows.append(z[i, 0] * 0.0)
            weights.append(0.0)
            continue
        w = float(weight[y[i]]) if weight is not None else 1.0
        rows.append(w * (torch.log(torch.exp(z[i]).sum()) - z[i, y[i]]))
        weights.append(w)
    per = torch.stack(rows)
    if reduction == "none":
        return per.reshape(target.shape)
    if reduction == "sum":
        return per.sum()
    return per.sum() / sum(weights)


def _case(shape: str, weighted: bool, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(SHAPES[shape], dtype=D, generator=g) * 3
    k = logits.shape[1]
    target = torch.randint(0, k, logits.shape[:1] + logits.shape[2:], generator=g)
    target.view(-1)[::3] = IGNORE
    weight = None
    if weighted:
        weight = torch.rand(k, dtype=D, generator=g) + 0.1
        weight[1] = 0.0  # an empty class's weight
    return logits, target, weight


@pytest.mark.parametrize("reduction", ["mean", "sum", "none"])
@pytest.mark.parametrize("weighted", [False, True], ids=["plain", "weighted"])
@pytest.mark.parametrize("shape", list(SHAPES))
def test_weighted_cross_entropy_equals_f_cross_entropy(shape: str, weighted: bool, reduction: str, device) -> None:
    """Values and gradients (float64) equal F.cross_entropy's on the CPU and the naive sum, whichever form runs."""
    logits, target, weight = _case(shape, weighted)
    upstream = torch.randn(target.shape, dtype=D) if reduction == "none" else torch.tensor(1.0, dtype=D)
    x = logits.clone().requires_grad_()
    want = F.cross_entropy(x, target, weight=weight, ignore_index=IGNORE, reduction=reduction)
    (want_grad,) = torch.autograd.grad(want, x, upstream)
    y = logits.clone().requires_grad_()
    naive = naive_ce(y, target, weight, IGNORE, reduction)
    (naive_grad,) = torch.autograd.grad(naive, y, upstream)
    torch.testing.assert_close(want, naive, rtol=1e-12, atol=1e-14)  # the reference itself
    torch.testing.assert_close(want_grad, naive_grad, rtol=1e-12, atol=1e-14)
    for deterministic in (True, None, False):
        xd = logits.to(device).requires_grad_()
        got = weighted_cross_entropy(xd, target.to(device), None if weight is None else weight.to(device), IGNORE,
                                     reduction, deterministic)
        (got_grad,) = torch.autograd.grad(got, xd, upstream.to(device))
        torch.testing.assert_close(got.detach().cpu(), want, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(got_grad.cpu(), want_grad, rtol=1e-12, atol=1e-14)


def test_weighted_cross_entropy_gradcheck(device) -> None:
    logits, target, weight = _case("5d", True, seed=1)
    x = logits.to(device).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda z: weighted_cross_entropy(z, target.to(device), weight.to(device), IGNORE, deterministic=True), (x,),
        fast_mode=True)


@pytest.mark.parametrize("weighted", [False, True], ids=["plain", "weighted"])
def test_weighted_cross_entropy_edge_cases_as_f_cross_entropy(weighted: bool, device) -> None:
    """Every position ignored ('mean' NaN, 'sum' 0, zero gradients), an ignore label inside [0, K), every counted
    label of weight 0 ('mean' NaN): as F.cross_entropy."""
    logits, target, weight = _case("5d", weighted, seed=2)
    cases = [(torch.full_like(target, IGNORE), IGNORE), (target.clamp(max=3), 0)]
    if weighted:
        cases.append((torch.ones_like(target), IGNORE))  # class 1 has weight 0
    for labels, ignore_index in cases:
        for reduction in ("mean", "sum", "none"):
            x = logits.clone().requires_grad_()
            want = F.cross_entropy(x, labels, weight=weight, ignore_index=ignore_index, reduction=reduction)
            (want_grad,) = torch.autograd.grad(want.sum(), x)
            xd = logits.to(device).requires_grad_()
            got = weighted_cross_entropy(xd, labels.to(device), None if weight is None else weight.to(device),
                                         ignore_index, reduction, deterministic=True)
            (got_grad,) = torch.autograd.grad(got.sum(), xd)
            torch.testing.assert_close(got.detach().cpu(), want, rtol=1e-12, atol=1e-14, equal_nan=True)
            torch.testing.assert_close(got_grad.cpu(), want_grad, rtol=1e-12, atol=1e-14, equal_nan=True)


def test_weighted_cross_entropy_keeps_the_cpus_bits_and_rejects_a_bad_reduction() -> None:
    """On the CPU the default form is PyTorch's fused one (deterministic there, and faster), bit for bit."""
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(2, 5, 4, 3, 2, generator=g)
    target = torch.randint(0, 5, (2, 4, 3, 2), generator=g)
    target[0, 0] = IGNORE
    weight = torch.rand(5, generator=g)
    assert torch.equal(weighted_cross_entropy(logits, target, weight, IGNORE),
                       F.cross_entropy(logits, target, weight=weight, ignore_index=IGNORE))
    with pytest.raises(ValueError, match="reduction"):
        weighted_cross_entropy(logits, target, reduction="batchmean")  # type: ignore[arg-type]


def test_the_losses_run_under_strict_deterministic_algorithms(device) -> None:
    """Forward and backward of every loss changed here, with ``use_deterministic_algorithms(True)`` (errors, not
    warnings): nothing they run is flagged on the device."""
    from distilkit.losses.ssc import weighted_ce

    g = torch.Generator().manual_seed(4)
    k = 5
    logits = torch.randn(2, k, 4, 4, 2, generator=g).to(device).requires_grad_()
    target = torch.randint(0, k, (2, 4, 4, 2), generator=g)
    target[0, 0] = IGNORE
    target = target.to(device)
    weight = (torch.rand(k, generator=g) + 0.1).to(device)
    lga = L.local_geometric_anisotropy(target)
    binary = torch.randn(2, 2, 2, 2, 1, generator=g).to(device).requires_grad_()
    points = torch.randn(30, k, generator=g).to(device).requires_grad_()
    point_labels = torch.randint(0, k, (30,), generator=g).to(device)
    with strict_determinism():
        for shape, (x, y) in {"2d": (points, point_labels), "5d": (logits, target)}.items():
            for w in (None, weight):
                for reduction in ("mean", "sum", "none"):
                    weighted_cross_entropy(x, y, w, IGNORE, reduction).sum().backward()
        terms = [L.cross_entropy(logits, target, weight=weight), L.cross_entropy(logits, target),
                 L.lovasz_softmax(logits, target), L.lovasz_softmax(logits, target, classes="all"),
                 L.occupancy_ce(binary, target), weighted_ce(logits, target, weight, "weight"),
                 weighted_ce(logits, target, weight, "valid"), L.geometry_weighted_ce(logits, target, weight, lga),
                 L.hard_voxel_ce(logits.flatten(2), target.flatten(1), lga.flatten(1), weight)]
        coords = torch.rand(2, 20, 3, generator=g).to(device)
        terms += [L.voxel_sample(logits, coords).sum(), L.voxel_sample(logits, coords, "nearest").sum(),
                  L.depth_l1(logits[:, 0, :, :, 0], torch.rand(2, 9, 7, generator=g).to(device) * 50, 80.0)]
        torch.stack(terms).sum().backward()
        ids = torch.arange(0, 2 * 8 * 8 * 2, 3, device=device)
        torch.multinomial(supervoxel_draw_weight(ids, 8, 8, 2), 5, replacement=False)
    assert logits.grad is not None and bool(torch.isfinite(logits.grad).all())


def _flagged(fn) -> str | None:
    """The error PyTorch raises for ``fn`` under strict deterministic algorithms, or None."""
    with strict_determinism():
        try:
            fn()
        except RuntimeError as e:
            return str(e)
    return None


@pytest.mark.parametrize("op", ["nll_loss2d", "index_reduce", "cumsum", "grid_sample", "interpolate"])
def test_pytorch_flags_what_the_forms_replace(op: str, device) -> None:
    """What PyTorch says of the forms replaced (the reason for each form): nothing on the CPU; on CUDA the flag, or
    — a version that no longer flags one — a warning naming it (the form is kept for the versions that do)."""
    g = torch.Generator().manual_seed(5)
    x = torch.randn(2, 4, 3, 2, 2, generator=g).to(device)
    if op == "nll_loss2d":  # F.cross_entropy's 'mean' over (B, K, X, Y, Z), weighted or not
        target = torch.randint(0, 4, (2, 3, 2, 2), generator=g).to(device)
        message = _flagged(lambda: F.cross_entropy(x, target, weight=torch.rand(4, device=device)))
    elif op == "index_reduce":  # PVKD's former draw
        inv = torch.randint(0, 3, (10,), generator=g).to(device)
        message = _flagged(lambda: torch.zeros(3, device=device).index_reduce_(0, inv, torch.rand(10, device=device),
                                                                               "amax", include_self=False))
    elif op == "cumsum":  # the Lovász-softmax's former running counts
        message = _flagged(lambda: torch.rand(1000, device=device).cumsum(0))
    elif op == "grid_sample":  # voxel_sample's former read, differentiated
        v = x.clone().requires_grad_()
        grid = torch.rand(2, 5, 1, 1, 3, device=device) * 2 - 1
        message = _flagged(lambda: F.grid_sample(v, grid, align_corners=False).sum().backward())
    else:  # depth_l1's former resize, differentiated
        v = x[:, 0].clone().requires_grad_()
        message = _flagged(lambda: F.interpolate(v, size=(7, 5), mode="bilinear", align_corners=False).sum().backward())
    if device.type != "cuda":
        assert message is None, message
        return
    if message is None:
        import warnings

        warnings.warn(f"torch {torch.__version__} does not flag the {op} form on {device}: the deterministic form is "
                      "not needed there (kept for the versions that do)")
        return
    assert "deterministic" in message, message


# ---- PVKD's draw ---------------------------------------------------------------------------------------------------
def index_reduce_draw_weight(groups: torch.Tensor, r_bin: torch.Tensor) -> torch.Tensor:
    """The earlier form: the largest radial bin + 1 over each supervoxel's voxels (``index_reduce_``, 'amax')."""
    ids, inv = torch.unique(groups, return_inverse=True)
    return torch.zeros(ids.numel(), device=ids.device).index_reduce_(0, inv, r_bin.float() + 1, "amax",
                                                                     include_self=False)


def _coords(g: torch.Generator, n: int, batch: int, shape: tuple[int, int, int]) -> torch.Tensor:
    cols = [torch.randint(0, batch, (n,), generator=g)] + [torch.randint(0, s, (n,), generator=g) for s in shape]
    return torch.unique(torch.stack(cols, 1), dim=0)


@INDEX_REDUCE_BETA
def test_pvkd_draw_weight_is_bitwise_the_index_reduce_form(device) -> None:
    g = torch.Generator().manual_seed(6)
    for trial in range(40):
        shape = tuple(int(v) for v in torch.randint(1, 33, (3,), generator=g))
        bins = tuple(int(v) for v in torch.randint(1, 9, (3,), generator=g))
        coords = _coords(g, int(torch.randint(1, 400, (1,), generator=g)), 1 + trial % 3, shape)
        groups, r_bin = L.supervoxel_ids(coords, shape, *bins)
        want = index_reduce_draw_weight(groups, r_bin)
        got = supervoxel_draw_weight(torch.unique(groups.to(device)), *bins).cpu()
        assert got.dtype == want.dtype and torch.equal(got, want), (shape, bins)
        # the same weights, so the same draw from the same generator state
        k = max(1, want.numel() // 2)
        a = torch.multinomial(want, k, generator=torch.Generator().manual_seed(trial))
        b = torch.multinomial(got, k, generator=torch.Generator().manual_seed(trial))
        assert torch.equal(a, b)


@INDEX_REDUCE_BETA
def test_pvkd_objective_draws_the_supervoxels_the_index_reduce_form_drew() -> None:
    """The objective with ``num_supervoxels``: the same value as PVKD over the supervoxels the earlier form draws
    from the same generator state."""
    from distilkit.data.batch import Batch
    from distilkit.objectives.relational import PVKD
    from distilkit.taps import SparseVoxels

    g = torch.Generator().manual_seed(7)
    coords = _coords(g, 300, 2, (16, 16, 4))
    fs = torch.randn(len(coords), 3, dtype=D, generator=g)
    ft = torch.randn(len(coords), 3, dtype=D, generator=g)
    obj = PVKD(PVKD.Params(output_weight=0.0, affinity_weight=1.0, radial_bins=3, angular_bins=2, height_bins=2,
                           num_supervoxels=4))
    logits = torch.zeros(2, 2, 16, 16, 4, dtype=D)
    batch = Batch({}, {"voxel_target": torch.zeros(2, 16, 16, 4, dtype=torch.long)}, {"size": 2})
    taps = {"student": SparseVoxels(coords, fs, (16, 16, 4)), "teacher": SparseVoxels(coords, ft, (16, 16, 4)),
            "student_logits": logits, "teacher_logits": logits, **obj.batch_roles(batch)}
    groups, r_bin = L.supervoxel_ids(coords, (16, 16, 4), 3, 2, 2)
    assert torch.unique(groups).numel() > 4
    torch.manual_seed(11)
    got = obj.compute(taps, batch)
    torch.manual_seed(11)
    chosen = torch.multinomial(index_reduce_draw_weight(groups, r_bin), 4, replacement=False)
    want = L.pvkd_affinity(fs, ft, groups, chosen)
    assert torch.equal(got, want)


# ---- Lovász-softmax's running counts -------------------------------------------------------------------------------
def float_cumsum_lovasz(logits: torch.Tensor, labels: torch.Tensor, classes: str = "present") -> torch.Tensor:
    """The earlier form, verbatim but for its floating-point ``cumsum`` of the sorted one-hot labels."""
    k = logits.shape[1]
    probs = logits.softmax(dim=1).movedim(1, -1).reshape(-1, k)
    flat = labels.reshape(-1)
    keep = flat != IGNORE
    probs, flat = probs[keep], flat[keep].long()
    fg = F.one_hot(flat, k).to(probs.dtype)
    errors = (fg - probs).abs()
    errors_sorted, perm = torch.sort(errors, dim=0, descending=True)
    fg_sorted = fg.gather(0, perm)
    gts = fg_sorted.sum(0)
    inter = gts - fg_sorted.cumsum(0)
    union = gts + (1.0 - fg_sorted).cumsum(0)
    jaccard = 1.0 - inter / union
    jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]], dim=0)
    per_class = (errors_sorted * jaccard.detach()).sum(0)
    return per_class[gts > 0].mean() if classes == "present" else per_class.mean()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lovasz_integer_counts_are_bitwise_the_float_cumsum_form(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(8)
    for trial in range(30):
        b, k = int(torch.randint(1, 3, (1,), generator=g)), int(torch.randint(2, 8, (1,), generator=g))
        spatial = tuple(int(v) for v in torch.randint(1, 6, (3,), generator=g))
        scale = 0.0 if trial % 4 == 0 else 3.0  # 0: every error tied
        logits = (torch.randn((b, k) + spatial, generator=g) * scale).to(dtype)
        labels = torch.randint(0, k, (b,) + spatial, generator=g)
        labels[torch.rand(labels.shape, generator=g) < 0.2] = IGNORE
        if not bool((labels != IGNORE).any()):
            continue
        for classes in ("present", "all"):
            x, y = logits.clone().requires_grad_(), logits.clone().requires_grad_()
            got, want = L.lovasz_softmax(x, labels, classes=classes), float_cumsum_lovasz(y, labels, classes)
            assert torch.equal(got, want), (trial, classes)
            assert torch.equal(torch.autograd.grad(got, x)[0], torch.autograd.grad(want, y)[0]), (trial, classes)


def test_lovasz_on_device_matches_the_float64_form(device) -> None:
    from conftest import on_device_matches

    g = torch.Generator().manual_seed(9)
    logits = torch.randn(2, 5, 6, 4, 3, dtype=D, generator=g, requires_grad=True)
    labels = torch.randint(0, 4, (2, 6, 4, 3), generator=g)
    labels[0, :2] = IGNORE
    on_device_matches(lambda z, y: L.lovasz_softmax(z, y), float_cumsum_lovasz, (logits, labels), device, rel=1e-12)


# ---- voxel_sample and resize_bilinear ------------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["bilinear", "nearest"])
def test_voxel_sample_by_gather_equals_grid_sample(mode: str, device) -> None:
    """Values and gradients (float64) of the gather form on the device equal grid_sample's on the CPU, positions
    outside the volume (zeros) and on voxel centres and edges (ties of ``nearest``) included."""
    g = torch.Generator().manual_seed(10)
    volume = torch.randn(2, 3, 5, 4, 6, dtype=D, generator=g, requires_grad=True)
    coords = torch.rand(2, 60, 3, dtype=D, generator=g) * 1.2 - 0.1
    coords[:, :8] = torch.tensor([[0.0, 0.5, 1.0], [0.1, 0.25, 0.5], [0.5, 0.5, 0.5], [0.3, 0.125, 0.75]] * 2, dtype=D)
    upstream = torch.randn(2, 3, 60, dtype=D, generator=g)
    want = L.voxel_sample(volume, coords, mode, deterministic=False)
    (want_grad,) = torch.autograd.grad(want, volume, upstream)
    here = volume.detach().to(device).requires_grad_()
    got = L.voxel_sample(here, coords.to(device), mode, deterministic=True)
    (got_grad,) = torch.autograd.grad(got, here, upstream.to(device))
    torch.testing.assert_close(got.detach().cpu(), want, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(got_grad.cpu(), want_grad, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("sizes", [((5, 7), (11, 13)), ((12, 10), (5, 4)), ((3, 3), (3, 9)), ((24, 77), (93, 306))])
def test_resize_bilinear_by_matrices_equals_interpolate(sizes, device) -> None:
    """Up and down, values and gradients (float64), against F.interpolate on the CPU."""
    (h, w), (big_h, big_w) = sizes
    g = torch.Generator().manual_seed(11)
    x = torch.randn(2, h, w, dtype=D, generator=g, requires_grad=True)
    upstream = torch.randn(2, big_h, big_w, dtype=D, generator=g)
    want = F.interpolate(x[:, None], size=(big_h, big_w), mode="bilinear", align_corners=False)[:, 0]
    (want_grad,) = torch.autograd.grad(want, x, upstream)
    here = x.detach().to(device).requires_grad_()
    got = resize_bilinear(here, (big_h, big_w), deterministic=True)
    (got_grad,) = torch.autograd.grad(got, here, upstream.to(device))
    torch.testing.assert_close(got.detach().cpu(), want, rtol=1e-12, atol=1e-13)
    torch.testing.assert_close(got_grad.cpu(), want_grad, rtol=1e-12, atol=1e-13)


def test_the_gather_and_matrix_forms_work_in_float32_for_bfloat16(device) -> None:
    """A bfloat16 volume or depth map (autocast's outputs): positions, weights and sums in float32, so the result is
    the float32 one rounded to bfloat16, not positions rounded to bfloat16's 8 bits."""
    g = torch.Generator().manual_seed(12)
    volume = torch.randn(1, 2, 64, 64, 8, generator=g).to(device)
    coords = torch.rand(1, 100, 3, generator=g).to(device)
    want = L.voxel_sample(volume, coords, deterministic=True).to(torch.bfloat16)
    got = L.voxel_sample(volume.to(torch.bfloat16), coords, deterministic=True)
    assert got.dtype == torch.bfloat16
    torch.testing.assert_close(got.float(), want.float(), rtol=1e-2, atol=2e-2)
    depth = torch.rand(1, 24, 77, generator=g).to(device) * 80
    want = resize_bilinear(depth, (93, 306), deterministic=True).to(torch.bfloat16)
    got = resize_bilinear(depth.to(torch.bfloat16), (93, 306), deterministic=True)
    assert got.dtype == torch.bfloat16
    torch.testing.assert_close(got.float(), want.float(), rtol=1e-2, atol=0.5)


# ---- the objectives' resampling of a feature map (FitNets, NST, MGD, region terms) ---------------------------------

@pytest.mark.parametrize("shape,target", [((2, 3, 8, 6, 4), (4, 3, 2)), ((2, 3, 7, 5, 3), (3, 2, 2)),
                                          ((2, 3, 4, 3, 2), (8, 6, 5)), ((2, 3, 4, 3, 2), (4, 6, 2)),
                                          ((2, 3, 9, 7), (4, 3)), ((2, 3, 3, 4), (7, 9))])
def test_match_spatials_matrix_form_equals_pooling_and_interpolation(shape, target, device) -> None:
    """Adaptive average pooling down and trilinear/bilinear interpolation up (PyTorch's kernels on the CPU, float64)
    against the separable matrix form used on CUDA under the deterministic settings: values and gradients, and the
    matrix form raises nothing with ``torch.use_deterministic_algorithms(True)`` on the test's device."""
    from distilkit.objectives.common import match_spatial

    g = torch.Generator().manual_seed(11)
    x = torch.randn(*shape, dtype=torch.float64, generator=g, requires_grad=True)
    want = match_spatial(x, target, deterministic=False)
    w = torch.randn(want.shape, dtype=torch.float64, generator=g)
    (grad_want,) = torch.autograd.grad((want * w).sum(), x)
    here = x.detach().to(device).requires_grad_()
    with strict_determinism():
        got = match_spatial(here, target, deterministic=True)
        (grad_got,) = torch.autograd.grad((got * w.to(device)).sum(), here)
    torch.testing.assert_close(got.cpu(), want, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad_got.cpu(), grad_want, rtol=1e-12, atol=1e-12)
