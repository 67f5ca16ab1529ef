"""The EMA-teacher edge (``teacher: {ema: ...}``, HASSC's mean teacher): its schema, the momentum schedule and the
update against a naive float64 recurrence, both buffer choices, its mode, and a killed run that resumes to the
same bits."""

from __future__ import annotations

import signal
import sys
import time

import pytest
import torch
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import make_trainer, process_context, tiny_recipe
from distilkit.cli import main
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.weights import load_checkpoint


def ema_recipe(steps: int = 3, **ema) -> dict:
    recipe = tiny_recipe(steps=steps, distill=False)
    stage = recipe["stages"].pop("teacher")
    stage["teacher"] = {"ema": ema or True}
    stage["distill"] = [{"name": "hassc_kd"}]
    recipe["stages"]["student"] = stage
    return recipe


def pipeline(tmp_path, recipe: dict) -> Pipeline:
    return Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)


def test_the_schema_takes_true_or_settings_and_names_a_second_source() -> None:
    spec = recipe_from_dict(ema_recipe()).stages["student"].teacher
    assert spec.ema is not None and (spec.ema.momentum, spec.ema.buffers, spec.ema.mode) == (0.99, "average", "eval")
    both = ema_recipe()
    both["stages"]["student"]["teacher"]["from"] = "student"
    with pytest.raises(RecipeError, match="exactly one of .*got from, ema"):
        recipe_from_dict(both)
    with pytest.raises(RecipeError, match="momentum"):
        recipe_from_dict(ema_recipe(momentum=1.0))
    model = ema_recipe()
    model["stages"]["student"]["teacher"]["model"] = {"adapter": "scpnet"}
    with pytest.raises(RecipeError, match="leave out `model`"):
        recipe_from_dict(model)


def _steps(trainer, n: int) -> list[dict[str, torch.Tensor]]:
    """The student's state dict before each of ``n`` steps (what each EMA update reads), float64."""
    seen = []
    for step in range(n):
        seen.append({k: v.detach().double().clone() for k, v in trainer.student.state_dict().items()})
        trainer.train_step(trainer.prepare(trainer.plan.batch(trainer.train_set, trainer.collate, step)), step)
    return seen


@pytest.mark.parametrize("buffers", ["average", "copy_once"])
def test_the_teacher_is_the_naive_moving_average_of_the_student(tmp_path, device, buffers: str) -> None:
    """t_0 = s_0; before step k: t = m_k t + (1 - m_k) s_k with m_k = min(1 - 1/(k+1), cap): the float64 recurrence
    on the student's states. Parameters always; floating buffers too with ``average``, never with ``copy_once``."""
    cap = 0.6  # reached at step 3 (m = 0, 1/2, 0.6, 0.6): the cap is exercised
    pipe = pipeline(tmp_path, ema_recipe(momentum=cap, buffers=buffers))
    trainer = make_trainer(pipe, "student", device=device)
    assert trainer.ema is not None and trainer.teacher is trainer.ema.model
    assert not trainer.teacher.training and not any(p.requires_grad for p in trainer.teacher.parameters())
    assert [trainer.ema.momentum(k) for k in range(5)] == [0.0, 0.5, 0.6, 0.6, 0.6]
    seen = _steps(trainer, 4)
    expected = {k: v.clone() for k, v in seen[0].items()}
    for k, state in enumerate(seen):
        m = min(1 - 1 / (k + 1), cap)
        for name, v in state.items():
            expected[name] = m * expected[name] + (1 - m) * v
    teacher = trainer.teacher.state_dict()
    params = {n for n, _ in trainer.student.named_parameters()}
    moved = [n for n in params if not torch.equal(seen[0][n], seen[-1][n])]
    assert moved  # the student trained, so the average means something
    for name in params:
        torch.testing.assert_close(teacher[name].double().cpu(), expected[name].cpu(), rtol=1e-5, atol=1e-6)
    stats = [n for n in teacher if n.endswith("running_mean")]
    assert stats, "the tiny SCPNet has BatchNorm statistics"
    for name in stats:
        want = expected[name] if buffers == "average" else seen[0][name]
        torch.testing.assert_close(teacher[name].double().cpu(), want.cpu(), rtol=1e-5, atol=1e-6)
    assert not torch.equal(seen[0][stats[0]], seen[-1][stats[0]])  # the student's statistics did move


def test_mode_train_runs_the_teacher_in_train_mode_and_the_default_in_eval(tmp_path) -> None:
    trainer = make_trainer(pipeline(tmp_path / "a", ema_recipe(mode="train")), "student")
    assert trainer.teacher.training and not any(p.requires_grad for p in trainer.teacher.parameters())
    logged = trainer.train_step(trainer.prepare(trainer.plan.batch(trainer.train_set, trainer.collate, 0)), 0)
    assert logged["ema_momentum"] == 0.0 and "kd_hassc_kd" in logged


def test_a_stage_without_distillation_builds_no_moving_average(tmp_path) -> None:
    recipe = ema_recipe()
    recipe["stages"]["student"]["distill"] = []
    trainer = make_trainer(pipeline(tmp_path, recipe), "student")
    assert trainer.ema is None and trainer.teacher is None


def test_a_killed_ema_run_resumes_to_the_same_bits(tmp_path) -> None:
    """SIGKILL (a real one, to a ``distilkit run`` process forked from this one) after the first checkpoint, then
    the same command again (in-process): the student and the EMA teacher of ``last.pt`` equal an uninterrupted run's
    bit for bit (the average is part of the checkpoint). All three with one thread: the same reductions in each,
    and GNU OpenMP in a forked child hangs on more threads than one once its parent has used them."""
    import os

    recipe = ema_recipe(steps=4)
    recipe["stages"]["student"]["train"]["eval_every"] = 4
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    out = tmp_path / "runs"
    argv = ["run", str(path), "--output", str(out), "--quiet"]
    run_dir = pipeline(tmp_path, recipe).run_dir("student")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        proc = process_context().Process(target=_run_quietly, args=(argv,))  # spawned on a GPU machine
        proc.start()
        try:
            t0 = time.monotonic()
            while not (run_dir / "checkpoints" / "last.pt").is_file() and proc.is_alive() \
                    and time.monotonic() - t0 < 120:
                time.sleep(0.005)
        finally:
            os.kill(proc.pid, signal.SIGKILL)
            proc.join()
        killed_at = load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"]
        assert 1 <= killed_at < 4, "the kill came after the first checkpoint and before the end"
        # the same command again, in this process (the same threads as the killed one): the kill needs a process
        assert main(argv) == 0
        (clean,) = pipeline(tmp_path / "clean", recipe).run()
    finally:
        torch.set_num_threads(threads)
    a = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    b = load_checkpoint(clean.run_dir / "checkpoints" / "last.pt")
    assert a["step"] == b["step"] == 4
    for part in ("student", "ema_teacher"):
        assert a[part].keys() == b[part].keys()
        assert all(torch.equal(a[part][k], b[part][k]) for k in a[part]), part
    assert not all(torch.equal(a["student"][k], a["ema_teacher"][k]) for k in a["student"])


def _run_quietly(argv: list[str]) -> None:
    """``distilkit ARGV`` in a child process (one thread, as its parent set), its output thrown away."""
    import os

    torch.set_num_threads(1)
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.dup2(null, 2)
    sys.exit(main(argv))
