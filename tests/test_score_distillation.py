"""ScoreLiDAR's VSD options (aux update order, key points per step, frozen scan encoder) and the Distillation-DPO
objective, on small LiDiff models."""

from __future__ import annotations

import pytest
import torch

from distilkit.data.batch import Batch
from distilkit.metrics.points import chamfer_distance
from distilkit.registry import ADAPTERS, OBJECTIVES
from distilkit.term import TermContext

DATA = {"num_train": 2, "num_val": 1, "num_test": 1, "scan_points": 16, "scene_points": 64, "frames": 3, "beams": 8,
        "azimuth_steps": 128}
SMALL = {"channels": 8, "blocks": 1, "duplicate": 4, "sample_steps": 1, "generate_steps": 1}


def lidiff(**kw):
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info

    cls = ADAPTERS.get("lidiff")
    torch.manual_seed(0)
    return cls(cls.Params(**{**SMALL, **kw}), scenes_info(SceneParams(**DATA)))


def batch(b: int = 2) -> Batch:
    g = torch.Generator().manual_seed(1)
    scan = torch.randn(b, 16, 3, generator=g) * 5
    scene = scan.repeat(1, 4, 1) + 0.2 * torch.randn(b, 64, 3, generator=g)
    return Batch({"scan": scan, "scan_lengths": torch.full((b,), 16)},
                 {"scene": scene, "scene_lengths": torch.full((b,), 64)}, {"size": b, "scene_id": ["a", "b"][:b]})


def bound(name: str, student, teacher, **params):
    entry = OBJECTIVES.entry(name)
    term = entry.obj(entry.obj.Params(**params))
    term.context = TermContext(student=student, teacher=teacher.eval(), device=torch.device("cpu"))
    return term


def test_the_few_step_students_scan_encoder_is_frozen_by_default() -> None:
    assert not any(p.requires_grad for p in lidiff().net.encoder.parameters())
    assert all(p.requires_grad for p in lidiff(generate_steps=0).net.encoder.parameters())
    assert all(p.requires_grad for p in lidiff(freeze_encoder=False).net.encoder.parameters())


@pytest.mark.parametrize("order", ["before", "after"])
def test_the_auxiliary_network_steps_before_the_student_by_default(order: str) -> None:
    teacher, student = lidiff(generate_steps=0), lidiff().train()
    term = bound("vsd", student, teacher, aux="lora", rank=2, aux_lr=0.1, aux_optimizer="adam", aux_update=order)
    b = batch()
    out = student(b)
    taps = {"student": out["samples"], "condition": b.inputs["scan"]}
    term.setup(taps, b)
    term.own_optimizer()
    lora = [p for n, p in term.aux.named_parameters() if n.endswith("lora_b")]
    term.compute(taps, b)
    moved_in_compute = any(float(p.detach().abs().max()) > 0 for p in lora)  # B starts at zero
    logged = term.update(0, b, {k: v.detach() for k, v in taps.items()})
    assert moved_in_compute == (order == "before") and "vsd_aux_loss" in logged
    assert any(float(p.detach().abs().max()) > 0 for p in lora)


def test_key_points_are_redrawn_every_step_or_cached_per_scene() -> None:
    teacher = lidiff(generate_steps=0)
    b = batch(1)
    scene = b.targets["scene"][0]
    per_step = bound("structural", None, teacher, k=4, sample_ratio=0.5)
    torch.manual_seed(0)
    draws = {tuple(per_step.keypoints(scene, "a").tolist()) for _ in range(5)}
    cached = bound("structural", None, teacher, k=4, sample_ratio=0.5, keypoints="cached")
    once = {tuple(cached.keypoints(scene, "a").tolist()) for _ in range(5)}
    assert len(draws) > 1 and len(once) == 1


def test_distillation_dpo_ranks_the_pair_and_sends_the_intended_gradient() -> None:
    teacher, student = lidiff(generate_steps=0), lidiff().train()
    term = bound("distillation_dpo", student, teacher, aux="lora", rank=2, aux_lr=0.01, aux_optimizer="adam",
                 aux_sample="same")
    b = batch()
    out = student(b)
    taps = {"student": out["samples"], "noise": out["start_noise"], "condition": b.inputs["scan"],
            "target": b.targets["scene"], "target_lengths": b.targets["scene_lengths"]}
    term.setup(taps, b)
    term.own_optimizer()
    # the pair: the second completion is the student's generator from 1.1 eps; the winner has the lower CD
    first = out["samples"].points
    second = student.generate(b.inputs["scan"], 1.1 * out["start_noise"].points)
    with torch.no_grad():
        again = student.generate(b.inputs["scan"], out["start_noise"].points)
    assert torch.allclose(again, first, atol=1e-6)
    from distilkit.structures import PointCloud

    target = PointCloud(b.targets["scene"], b.targets["scene_lengths"])
    winner, loser, first_wins = term.pair(first, second, target)
    for i in range(2):
        d1, d2 = chamfer_distance(first[i], target.cloud(i)), chamfer_distance(second[i], target.cloud(i))
        assert bool(first_wins[i]) == (d1 <= d2)
        assert torch.equal(winner[i], first[i] if d1 <= d2 else second[i])
    # the gradient reaches the student through both completions and equals the formula's
    first_leaf = first.detach().requires_grad_()
    second_leaf = second.detach().requires_grad_()
    gen = lambda cond, noise: second_leaf  # noqa: E731
    student.generate = gen  # type: ignore[method-assign]
    import copy

    term2 = copy.deepcopy(term)  # the same auxiliary networks and optimizer state, for the replay
    torch.manual_seed(5)
    loss = term.compute({**taps, "student": PointCloud(first_leaf, out["samples"].lengths)}, b)
    loss.backward()
    assert first_leaf.grad.abs().max() > 0 and second_leaf.grad.abs().max() > 0
    torch.manual_seed(5)  # replay: the aux step (before) and the re-noising draw from the same stream
    w, l_, wins = term2.pair(first_leaf.detach(), second_leaf.detach(), target)
    term2.fit_aux([(term2.aux, w), (term2.aux_loser, l_)], b.inputs["scan"])
    x_w, t, eps = term2._noised(w)
    x_l = l_ + (x_w - w)
    with torch.no_grad():
        g_w = teacher.predict_noise(x_w, t, b.inputs["scan"]) - term2.aux.predict_noise(x_w, t, b.inputs["scan"])
        g_l = teacher.predict_noise(x_l, t, b.inputs["scan"]) - term2.aux_loser.predict_noise(x_l, t, b.inputs["scan"])
    n = first.numel()
    pick = wins[:, None, None]
    want_first = torch.where(pick, g_w, -g_l) / n
    want_second = torch.where(pick, -g_l, g_w) / n
    assert torch.allclose(first_leaf.grad, want_first, atol=1e-7)
    assert torch.allclose(second_leaf.grad, want_second, atol=1e-7)
    logged = term.update(0, b, taps)
    assert set(logged) == {"dpo_first_wins", "dpo_aux_loss"}


def test_the_auxiliary_network_is_a_trainable_copy_of_the_teacher_by_default() -> None:
    """ScoreLiDAR appendix A.3 and its code: a full copy initialised from the teacher (LoRA is an option)."""
    teacher, student = lidiff(generate_steps=0), lidiff().train()
    for name in ("vsd", "distillation_dpo"):
        term = bound(name, student, teacher)
        b = batch()
        out = student(b)
        term.setup({"student": out["samples"], "condition": b.inputs["scan"]}, b)
        for aux in term.aux_networks():
            mine, theirs = dict(aux.named_parameters()), dict(teacher.named_parameters())
            assert mine.keys() == theirs.keys() and all(p.requires_grad for p in mine.values())
            assert all(torch.equal(mine[k], theirs[k]) and mine[k] is not theirs[k] for k in mine)
    lora = bound("vsd", student, teacher, aux="lora", rank=2)
    lora.setup({"student": out["samples"], "condition": b.inputs["scan"]}, b)
    assert any(n.endswith("lora_a") for n, _ in lora.aux.named_parameters())


def test_the_auxiliary_step_fits_a_fresh_student_sample() -> None:
    """The release's aux step generates its own samples (no gradient, eval mode): not the ones it is queried on."""
    teacher, student = lidiff(generate_steps=0), lidiff().train()
    b = batch()
    out = student(b)
    x0, cond = out["samples"].points, b.inputs["scan"]
    for sample, want_fresh in (("fresh", True), ("same", False)):
        term = bound("vsd", student, teacher, aux_sample=sample)
        taps = {"student": out["samples"], "condition": cond}
        term.setup(taps, b)
        term.own_optimizer()
        seen = []
        term.fit_aux = lambda pairs, condition: seen.extend(x for _, x in pairs)  # type: ignore[method-assign]
        torch.manual_seed(3)
        term.compute(taps, b)
        torch.manual_seed(3)
        with torch.no_grad():
            fresh = student.generate(cond, torch.randn_like(x0))
        assert torch.equal(seen[0], fresh) == want_fresh and torch.equal(seen[0], x0) != want_fresh
        assert student.training  # the mode is restored after the eval-mode sample
    # the recipe checks the capability: a fresh sample calls the student's generate()
    from distilkit.objectives.score import VSD

    assert VSD.student_requires(VSD.Params()) == {"generate"}
    assert VSD.student_requires(VSD.Params(aux_sample="same")) == frozenset()
