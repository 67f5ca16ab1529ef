"""A frozen teacher's mode (``teacher: {mode: eval | train}``, :mod:`distilkit.engine.train.teacher_mode`): the schema
(one mode for an EMA teacher, either spelling), the stage identity, what train mode computes (batch statistics, the
running statistics moved once per step and not by the setup pass), and a stopped run that resumes to the same bits."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from conftest import make_trainer, tiny_recipe
from distilkit.engine.assemble.runs import build_model, freeze
from distilkit.engine.train.distributed import World
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.train.teacher_mode import apply_mode, evaluating
from distilkit.errors import RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.weights import load_checkpoint


def moded(mode: str | None, steps: int = 2) -> dict:
    recipe = tiny_recipe(steps=steps)
    if mode is not None:
        recipe["stages"]["student"]["teacher"]["mode"] = mode
    return recipe


def pipeline(path, recipe: dict) -> Pipeline:
    return Pipeline(recipe_from_dict(recipe), path / "runs", quiet=True)


def ema(**teacher) -> dict:
    recipe = tiny_recipe(distill=False)
    stage = recipe["stages"].pop("teacher")
    stage.update(teacher=teacher, distill=[{"name": "hassc_kd"}])
    recipe["stages"]["student"] = stage
    return recipe


def test_the_schema_defaults_to_eval_names_a_bad_mode_and_gives_an_ema_teacher_one_mode() -> None:
    assert recipe_from_dict(moded(None)).stages["student"].teacher.mode == "eval"
    assert recipe_from_dict(moded("train")).stages["student"].teacher.mode == "train"
    with pytest.raises(RecipeError, match="mode"):
        recipe_from_dict(moded("training"))
    # `mode` beside `ema` and `ema.mode` are one setting: both spellings give the same spec (and so the same hash)
    a = recipe_from_dict(ema(ema=True, mode="train")).stages["student"].teacher
    b = recipe_from_dict(ema(ema={"mode": "train"})).stages["student"].teacher
    assert (a.mode, a.ema.mode) == (b.mode, b.ema.mode) == ("train", "train")
    assert a.model_dump(exclude_defaults=True) == b.model_dump(exclude_defaults=True)
    assert recipe_from_dict(ema(ema=True)).stages["student"].teacher.ema.mode == "eval"
    with pytest.raises(RecipeError, match="disagree"):
        recipe_from_dict(ema(ema={"mode": "eval"}, mode="train"))


def test_only_train_mode_changes_the_stage_identity_and_the_teacher_stage_keeps_its_own(tmp_path) -> None:
    hashes = {m: pipeline(tmp_path / str(m), moded(m)).hashes for m in (None, "eval", "train")}
    assert hashes[None] == hashes["eval"]  # the default spelled out is the default: finished runs are reused
    assert hashes["train"]["student"] != hashes[None]["student"]
    assert hashes["train"]["teacher"] == hashes[None]["teacher"]


def _teacher(pipe) -> nn.Module:
    """A frozen teacher as a stage loads one (eval mode, no gradients), with random weights."""
    torch.manual_seed(1)
    stage = pipe.resolved.stages["student"]
    return freeze(build_model(stage.teacher, pipe.resolved.data_info, role="teacher"))


def _statistics(model: nn.Module) -> dict[str, torch.Tensor]:
    return {n: b.detach().clone() for n, b in model.named_buffers() if "running" in n or "num_batches" in n}


@pytest.mark.parametrize("mode", ["eval", "train"])
def test_the_teacher_runs_in_its_mode_and_train_mode_moves_its_statistics_once_a_step(tmp_path, mode: str) -> None:
    """Train mode: the step's teacher outputs are a train-mode forward's (batch statistics; an independent copy run
    in train mode on the same batch gives the same bits), and the running statistics move exactly as that one
    forward moves the copy's — the setup pass (batch 0, in eval mode) moved none. Eval mode: nothing moves."""
    pipe = pipeline(tmp_path, moded(mode))
    given = _teacher(pipe)
    before = _statistics(given)
    assert before, "the tiny SCPNet has BatchNorm statistics"
    reference = copy.deepcopy(given)
    trainer = make_trainer(pipe, "student", teacher=given)
    assert trainer.teacher.training == (mode == "train")
    assert not any(p.requires_grad for p in trainer.teacher.parameters())
    after_setup = _statistics(trainer.teacher)
    assert all(torch.equal(after_setup[n], before[n]) for n in before)  # the setup pass moved nothing
    batch = trainer.prepare(trainer.plan.batch(trainer.train_set, trainer.collate, 0))
    outputs = trainer._teacher_outputs(batch)
    with torch.no_grad():
        expected = reference.train(mode == "train")(batch)
    tap = trainer.stage.distill[0].taps["teacher"]
    assert torch.equal(outputs[tap].feats, expected[tap].feats)
    with torch.no_grad():
        in_eval = copy.deepcopy(given).eval()(batch)  # the other mode gives other values: the mode is what decided
    moved = _statistics(trainer.teacher)
    if mode == "train":
        assert not torch.equal(outputs[tap].feats, in_eval[tap].feats)
        changed = [n for n in before if not torch.equal(moved[n], before[n])]
        assert changed and all(torch.equal(moved[n], _statistics(reference)[n]) for n in before)
    else:
        assert all(torch.equal(moved[n], before[n]) for n in before)


def test_a_trainer_resumed_from_its_state_continues_with_the_same_bits(tmp_path) -> None:
    """Two steps in one go against one, ``state()`` and the random state, then a new trainer with a teacher freshly
    loaded (as a resumed run builds it) that loads them and takes the second: the same student and statistics."""
    from distilkit.engine.train.randomness import rng_state, set_rng_state

    pipe = pipeline(tmp_path, moded("train"))
    teacher = _teacher(pipe)

    def trainer():
        torch.manual_seed(0)
        return make_trainer(pipe, "student", teacher=copy.deepcopy(teacher))

    def steps(t, first: int, last: int) -> None:
        for step in range(first, last):
            t.train_step(t.prepare(t.plan.batch(t.train_set, t.collate, step)), step)

    whole = trainer()
    steps(whole, 0, 2)
    half = trainer()
    steps(half, 0, 1)
    saved, rng = copy.deepcopy(half.state()), rng_state()
    resumed = trainer()
    resumed.load_state(saved)
    set_rng_state(rng)
    steps(resumed, 1, 2)
    a, b = whole.state(), resumed.state()
    for part in ("student", "teacher_buffers"):
        assert all(torch.equal(a[part][k], b[part][k]) for k in a[part]), part
    stats = [k for k in a["teacher_buffers"] if k.endswith("running_mean")]
    assert any(not torch.equal(saved["teacher_buffers"][k], a["teacher_buffers"][k]) for k in stats)  # step 2


@pytest.mark.slow
def test_a_stopped_train_mode_run_resumes_to_the_same_bits(tmp_path) -> None:
    """Stopped after 2 of 4 steps and started again: the student and the teacher's statistics of ``last.pt`` equal an
    uninterrupted run's bit for bit. The statistics did move, so a resume that rebuilt the teacher from its stage's
    checkpoint instead of ``last.pt`` would differ."""
    recipe = moded("train", steps=4)
    recipe["stages"]["teacher"]["train"] = {**recipe["stages"]["teacher"]["train"], "steps": 1, "eval_every": 1}
    whole = pipeline(tmp_path / "whole", recipe).run()
    pipeline(tmp_path / "resumed", recipe).run(stop_after=2)
    stopped = pipeline(tmp_path / "resumed", recipe).run_dir("student")
    first = load_checkpoint(stopped / "checkpoints" / "last.pt")
    assert first["step"] == 2 and "teacher_buffers" in first
    resumed = pipeline(tmp_path / "resumed", recipe).run()
    a = load_checkpoint(whole[-1].run_dir / "checkpoints" / "last.pt")
    b = load_checkpoint(resumed[-1].run_dir / "checkpoints" / "last.pt")
    assert a["step"] == b["step"] == 4
    for part in ("student", "teacher_buffers"):
        assert a[part].keys() == b[part].keys()
        assert all(torch.equal(a[part][k], b[part][k]) for k in a[part]), part
    upstream = load_checkpoint(whole[0].run_dir / "checkpoints" / "best.pt")["student"]
    stats = [k for k in a["teacher_buffers"] if k.endswith("running_mean")]
    assert stats and any(not torch.equal(a["teacher_buffers"][k], upstream[k]) for k in stats)
    assert any(not torch.equal(first["teacher_buffers"][k], a["teacher_buffers"][k]) for k in stats)  # steps 3-4


def test_an_eval_mode_teacher_adds_nothing_to_the_checkpoint_and_a_resume_without_buffers_is_named(tmp_path) -> None:
    pipe = pipeline(tmp_path, moded("eval"))
    assert "teacher_buffers" not in make_trainer(pipe, "student", teacher=_teacher(pipe)).state()
    trained = make_trainer(pipeline(tmp_path, moded("train")), "student", teacher=_teacher(pipe))
    state = trained.state()
    del state["teacher_buffers"]
    with pytest.raises(Exception, match="no teacher buffers"):
        trained.load_state(state)


def test_train_mode_synchronises_batchnorm_where_the_student_does(device) -> None:
    """Two processes on CUDA: SyncBatchNorm (the global batch's statistics, as the student's); on CPUs the layers
    stay (each process its share). Eval mode never converts. The block of :func:`evaluating` restores the mode."""
    world = World(rank=0, size=2)
    model = nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))
    trained = apply_mode(copy.deepcopy(model), "train", world, device)
    synced = any(isinstance(m, nn.SyncBatchNorm) for m in trained.modules())
    assert synced == (device.type == "cuda") and trained.training
    assert not any(isinstance(m, nn.SyncBatchNorm) for m in apply_mode(copy.deepcopy(model), "eval", world,
                                                                       device).modules())
    with evaluating(trained):
        assert not trained.training
    assert trained.training and not any(p.requires_grad for p in trained.parameters())
