"""Camera SSC task losses against naive loops over voxels and classes written from MonoScene's and VoxFormer's
definitions (seed_code.md §5), in float64, values and gradients, an absent class and empty ground truths included."""

from __future__ import annotations

import math

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
import distilkit.losses as L

IGN = 255


def naive_weighted_ce(logits, target, weight, normalize):
    b, k = logits.shape[:2]
    lp = torch.log_softmax(logits, 1).movedim(1, -1).reshape(-1, k)
    y = target.reshape(-1)
    num, n_valid, w_sum = 0.0, 0, 0.0
    for v in range(len(y)):
        if int(y[v]) == IGN:
            continue
        w = 1.0 if weight is None else weight[int(y[v])]
        num = num - w * lp[v, int(y[v])]
        n_valid += 1
        w_sum = w_sum + w
    return num / n_valid if normalize == "valid" else num / w_sum


def naive_geo_scal(logits, target):
    p = torch.softmax(logits, 1)
    q, occ, emp = [], [], []
    for v, y in enumerate(target.reshape(-1).tolist()):
        if y == IGN:
            continue
        q.append(1 - p.movedim(1, -1).reshape(-1, p.shape[1])[v, 0])
        occ.append(1.0 if y != 0 else 0.0)
    q, occ = torch.stack(q), torch.tensor(occ, dtype=logits.dtype)
    inter = (q * occ).sum()
    out = 0.0
    if occ.sum() > 0:
        out = out - torch.log(inter / q.sum()) - torch.log(inter / occ.sum())
    if (1 - occ).sum() > 0:
        out = out - torch.log(((1 - q) * (1 - occ)).sum() / (1 - occ).sum())
    return out


def naive_sem_scal(logits, target):
    """MonoScene's sem_scal_loss, class by class."""
    k = logits.shape[1]
    p = torch.softmax(logits, 1)
    mask = target != IGN
    loss, count = 0.0, 0
    for i in range(k):
        pi = p[:, i][mask]
        t = (target[mask] == i).to(logits.dtype)
        if t.sum() > 0:
            count += 1
            nom = (pi * t).sum()
            term = 0.0
            if pi.sum() > 0:
                term = term - torch.log(nom / pi.sum())
            term = term - torch.log(nom / t.sum())
            if (1 - t).sum() > 0:
                term = term - torch.log(((1 - pi) * (1 - t)).sum() / (1 - t).sum())
            loss = loss + term
    return loss / count


@pytest.fixture
def case():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 5, 4, 3, 2, dtype=torch.float64, generator=g, requires_grad=True)
    target = torch.randint(0, 5, (2, 4, 3, 2), generator=g)
    target[target == 3] = 2  # class 3 absent
    target[0, 0] = IGN
    return logits, target


def close(a, b, tol=1e-10):
    a, b = float(torch.as_tensor(a).detach()), float(torch.as_tensor(b).detach())
    return abs(a - b) <= tol * max(1.0, abs(b))


def grads(fn, logits):
    (g,) = torch.autograd.grad(fn(), logits)
    return g


def test_weighted_ce_in_both_normalisations_equals_the_loop(case) -> None:
    logits, target = case
    weight = torch.tensor([0.4, 1.0, 2.0, 3.0, 0.7], dtype=torch.float64)
    for normalize in ("valid", "weight"):
        for w in (None, weight):
            got = L.weighted_ce(logits, target, w, normalize)
            want = naive_weighted_ce(logits, target, w, normalize)
            assert close(got, want), (normalize, w)
            assert torch.allclose(grads(lambda: L.weighted_ce(logits, target, w, normalize), logits),
                                  grads(lambda: naive_weighted_ce(logits, target, w, normalize), logits))
    # the two modes differ by the per-batch scalar Σ w_y / N_valid
    valid = target != IGN
    ratio = weight[target[valid]].sum() / valid.sum()
    assert close(L.weighted_ce(logits, target, weight, "valid"), L.weighted_ce(logits, target, weight, "weight") * ratio)
    with pytest.raises(ValueError, match="normalize"):
        L.weighted_ce(logits, target, weight, "mean")


def test_geo_and_sem_scal_equal_monoscenes_loops_with_an_absent_class(case) -> None:
    logits, target = case
    assert not (target == 3).any()
    assert close(L.geo_scal(logits, target), naive_geo_scal(logits, target))
    assert close(L.sem_scal(logits, target), naive_sem_scal(logits, target))
    assert torch.allclose(grads(lambda: L.geo_scal(logits, target), logits),
                          grads(lambda: naive_geo_scal(logits, target), logits))
    assert torch.allclose(grads(lambda: L.sem_scal(logits, target), logits),
                          grads(lambda: naive_sem_scal(logits, target), logits))
    small = logits[:1, :, :2, :2, :1].detach().clone().requires_grad_(True)
    t = target[:1, :2, :2, :1]
    assert torch.autograd.gradcheck(lambda x: L.sem_scal(x, t), (small,))
    assert torch.autograd.gradcheck(lambda x: L.geo_scal(x, t), (small,))


def test_the_losses_stay_finite_when_the_ground_truth_is_empty(case) -> None:
    logits, _ = case
    empty = torch.zeros(2, 4, 3, 2, dtype=torch.long)  # every voxel empty: geo_scal's recall would be 0/0
    nothing = torch.full((2, 4, 3, 2), IGN)  # no valid voxel at all
    for target in (empty, nothing):
        for fn in (L.geo_scal, L.sem_scal, L.weighted_ce):
            value = fn(logits, target)
            assert math.isfinite(float(value.detach())), fn.__name__
            (g,) = torch.autograd.grad(value, logits)
            assert torch.isfinite(g).all()
    # with an empty scene, geo_scal is its specificity term (precision is 0 whatever is predicted, recall 0/0)
    q = 1 - torch.softmax(logits, 1)[:, 0]
    assert close(L.geo_scal(logits, empty), -torch.log(((1 - q)).sum() / q.numel()))
    assert float(L.sem_scal(logits, nothing).detach()) == 0.0


def test_partial_ce_reads_only_the_scribbled_classes(case) -> None:
    logits, target = case
    scribble = target.clone()
    scribble[0, 1] = 254  # unlabelled
    scribble[1, 2] = 0  # empty: not a class a scribble marks
    labelled = (scribble != IGN) & (scribble != 254) & (scribble != 0)
    want = naive_weighted_ce(logits, torch.where(labelled, scribble, torch.full_like(scribble, IGN)), None, "valid")
    assert close(L.partial_ce(logits, scribble), want)


def test_log_frequency_weights_are_voxformers_table() -> None:
    # MonoScene's SemanticKITTI class counts (empty, car, bicycle) and VoxFormer's weights for them
    counts = torch.tensor([5.41773033e09, 1.57835390e07, 1.25136000e05])
    assert torch.allclose(L.log_frequency_weights(counts), torch.tensor([0.446, 0.603, 0.852]), atol=1e-3)
    assert torch.allclose(L.log_frequency_weights(counts, scale=1.0), L.log_frequency_weights(counts) / 10)


def test_the_registered_task_losses_train_a_stage_by_name_with_weights_from_the_split(tmp_path) -> None:
    from conftest import tiny_recipe
    from distilkit.data.stats import label_counts
    from distilkit.engine.train.pipeline import Pipeline
    from distilkit.recipe import recipe_from_dict

    r = tiny_recipe(steps=2, distill=False)
    r["stages"]["teacher"]["task_losses"] = [{"name": "weighted_ce"}, {"name": "geo_scal"}, {"name": "sem_scal"},
                                             {"name": "partial_ce", "weight": 0.5}]
    pipe = Pipeline(recipe_from_dict(r), tmp_path / "runs", quiet=True)
    (teacher,) = pipe.run()
    log = (teacher.run_dir / "metrics.jsonl").read_text()
    assert all(f'"{k}"' in log for k in ("weighted_ce", "geo_scal", "sem_scal", "partial_ce"))
    from conftest import make_trainer

    trainer = make_trainer(pipe, "teacher")
    weight = trainer.task[0].weight
    counts, _ = label_counts(pipe.dataset("train"), len(weight))
    present = counts > 0
    assert torch.allclose(weight[present], L.log_frequency_weights(counts[present]))
    assert torch.allclose(weight[~present], weight[present].max().expand(int((~present).sum())))
    assert trainer.stage.task_losses[3].fields == {"target": "scribble"}  # partial CE reads the scribbles
