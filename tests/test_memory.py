"""Memory: `distilkit validate` estimates a stage's peak memory per training step and warns where it does not fit;
a stage that runs out of memory anyway ends in one line that names it and says what to lower, its checkpoint kept."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import tiny_recipe
from distilkit.cli import main
from distilkit.engine.memory import estimate as memory
from distilkit.engine.train import oom
from distilkit.weights import load_checkpoint
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.assemble.resolve import resolve
from distilkit.recipe import recipe_from_dict

GIB = 1024**3


def test_the_estimate_counts_weights_once_and_the_rest_per_sample() -> None:
    # on the CPU whatever --device says (tiny_recipe's default): the phases are compared in exact bytes, as the CPU
    # profiler's allocation events give them (the CUDA allocator rounds each block up)
    one, two = tiny_recipe(steps=1), tiny_recipe(steps=1)
    two["stages"]["teacher"]["train"]["batch_size"] = 2
    first = memory.estimate_stage(resolve(recipe_from_dict(one), "one"), "teacher")
    second = memory.estimate_stage(resolve(recipe_from_dict(two), "two"), "teacher")
    assert first is not None and second is not None
    assert first.how == "measured" and first.low == first.high and first.size == "a 32x32x4 grid"
    m = memory.measure_step(resolve(recipe_from_dict(one), "one"), "teacher",
                            first_scene := resolve(recipe_from_dict(one), "one").data_params)
    assert first_scene.scale == 8 and first.high == pytest.approx(m.total, rel=1e-6)
    assert 0 < m.kept < m.optimizer < m.model and m.temporaries > 0
    # the per-sample part of each phase twice; the optimizer's own temporaries once
    assert second.high == pytest.approx(max(m.kept + 2 * (m.model - m.kept),
                                            m.kept + 2 * (m.optimizer - m.kept) + m.temporaries), rel=1e-6)
    # a stage that does not train needs no estimate
    three = tiny_recipe(steps=1)
    three["stages"]["teacher"]["train"] = {"steps": 0}
    assert memory.estimate_stage(resolve(recipe_from_dict(three), "three"), "teacher") is None


def test_a_step_is_split_into_the_model_phase_and_the_optimizer_step() -> None:
    """Linear 512 -> 512 (1 MiB of weights) with Adam: the model phase holds the activations and the new gradients;
    the optimizer's first step starts with the gradients live and creates two state tensors per parameter."""
    import torch

    torch.manual_seed(0)
    model = torch.nn.Linear(512, 512)
    opt = torch.optim.Adam(model.parameters())
    x = torch.randn(256, 512)
    weights = sum(p.numel() * 4 for p in model.parameters())

    def step() -> None:
        loss = model(x).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    first = memory.step_peaks(step, torch.device("cpu"))  # the CPU profiler's phases, whatever --device says
    assert len(first.optimizer) == 1
    held, peak = first.optimizer[0]
    assert held >= weights  # the gradients, at least
    assert peak - held >= 2 * weights  # exp_avg and exp_avg_sq
    assert first.model >= 256 * 512 * 4 + weights  # the output and the gradients
    assert first.peak == max(first.model, peak)
    second = memory.step_peaks(step, torch.device("cpu"))  # the state exists now: the step allocates less
    assert second.optimizer[0][1] - second.optimizer[0][0] < peak - held
    assert memory.peak_of_step(step, torch.device("cpu")) == second.peak  # every later step is the same
    assert memory.step_peaks(lambda: model(x).sum().backward(), torch.device("cpu")).optimizer == []


def test_the_bounds_hold_for_any_mix_of_dense_sparse_and_fixed_parts() -> None:
    """Per-sample bytes that are a sum of parts growing as size^p, 0 <= p <= 1, or the larger of two such sums (two
    phases of a step): the bounds at 8 x the larger probe hold, and are exact for a pure power, a pure proportion and
    (a sum) a constant plus a proportion."""
    import random

    rng = random.Random(0)
    s1, s2, t = 32_768.0, 262_144.0, 2_097_152.0
    for _ in range(300):
        c, d, e = (rng.choice([0.0, rng.uniform(0, 1e9)]) for _ in range(3))
        p = rng.uniform(0, 1)
        if c + d + e == 0:
            continue
        parts = [c, d * (s1 / s2) ** p + e * s1 / s2, d * (s2 / s2) ** p + e, d * (t / s2) ** p + e * t / s2]
        total = lambda i: c + parts[i]  # noqa: E731
        biggest = lambda i: max(c, parts[i])  # noqa: E731
        for f, peak in ((total, False), (total, True), (biggest, True)):
            low, high = memory._bounds([(s1, f(1)), (s2, f(2))], t, peak)
            assert low <= f(3) * (1 + 1e-9) and f(3) <= high * (1 + 1e-9), (c, d, e, p, peak)
    assert memory._bounds([(s1, 2.0 * s1 ** 0.5), (s2, 2.0 * s2 ** 0.5)], t)[0] == pytest.approx(2.0 * t ** 0.5)
    assert memory._bounds([(s1, 3.0 * s1), (s2, 3.0 * s2)], t) == pytest.approx((3.0 * t, 3.0 * t))
    assert memory._bounds([(s1, 7.0 + s1), (s2, 7.0 + s2)], t, peak=False)[1] == pytest.approx(7.0 + t)
    assert memory._bounds([(s1, 7.0), (s2, 7.0)], t, peak=False) == (7.0, 7.0)
    assert memory._bounds([(s1, 7.0), (s2, 7.0)], t)[1] == pytest.approx(7.0 * t / s2)  # a hidden phase may grow
    assert memory._bounds([(s2, 5.0)], s2) == (5.0, 5.0)


def test_validate_prints_the_estimate_and_warns_when_the_step_does_not_fit(tmp_path: Path, capsys, monkeypatch,
                                                                         device) -> None:
    """Measured on the device the stages train on (the CPU profiler's allocations, or CUDA's allocator)."""
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(tiny_recipe(steps=1, device=device)))
    assert main(["validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "stage teacher: about" in out and \
        f"per training step on the {device.type} (batch 1, a 32x32x4 grid; measured)" in out
    assert "warning" not in out
    monkeypatch.setattr(memory, "available_memory", lambda device: 1024**2)  # a machine with 1 MiB free
    assert main(["validate", str(path)]) == 0  # advice, not an error
    out = capsys.readouterr().out
    assert "warning: stage teacher needs at least" in out and f"more than the 0.0 GiB free on the {device.type}" in out
    assert "lower train.batch_size (now 1), the grid (data.params.scale) or the size of scpnet's model" in out
    assert main(["validate", str(path), "--no-memory"]) == 0
    assert "per training step" not in capsys.readouterr().out


def test_an_extrapolated_estimate_is_a_range_and_the_warning_says_may() -> None:
    est = memory.MemoryEstimate("teacher", 12 * GIB, 25 * GIB, 2, "a 256x256x32 grid",
                                "extrapolated from 32,768 and 262,144 voxels", "cpu", 21 * GIB)
    assert est.figure == "12.0-25.0 GiB" and est.warning().startswith("stage teacher may need up to 25.0 GiB")
    assert memory.MemoryEstimate("t", 5 * GIB, 5.2 * GIB, 2, "", "", "cpu", 21 * GIB).warning() is None


def test_running_out_of_memory_is_one_line_and_keeps_the_checkpoint(tmp_path: Path, monkeypatch, capsys) -> None:
    recipe = tiny_recipe(steps=3, distill=False)
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))
    from distilkit.engine.train.trainer import Trainer

    real = Trainer.loss_terms
    calls = {"n": 0}

    def allocation_fails(self, batch):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate "
                               "memory: you tried to allocate 34359738368 bytes. Error code 12 (Cannot allocate memory)")
        return real(self, batch)

    monkeypatch.setattr(Trainer, "loss_terms", allocation_fails)
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    with pytest.raises(oom.OutOfMemoryError) as err:
        pipe.run()
    text = str(err.value)
    assert "\n" not in text and text.startswith("stage 'teacher' ran out of memory (an allocation of 32,768 MiB failed")
    assert "train.batch_size 1, a 32x32x4 grid, adapter scpnet" in text and "step 1) is kept" in text
    assert "Lower train.batch_size, the grid (data.params.scale) or the model's size" in text
    assert load_checkpoint(pipe.run_dir("teacher") / "checkpoints" / "last.pt")["step"] == 1
    calls["n"] = 0
    assert main(["run", str(path), "-o", str(tmp_path / "cli"), "-q"]) == 2
    err_text = capsys.readouterr().err
    assert err_text.startswith("error: stage 'teacher' ran out of memory") and "Traceback" not in err_text


def test_other_runtime_errors_are_not_taken_for_memory() -> None:
    assert oom.is_out_of_memory(MemoryError())
    assert oom.is_out_of_memory(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"))
    assert not oom.is_out_of_memory(RuntimeError("shape '[2, 3]' is invalid for input of size 5"))
    assert oom._cause(RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB (GPU 0)")) == \
        "an allocation of 2.00 GiB on the GPU failed"


@pytest.mark.slow  # 1.6 GiB: beside any other slow test (not in the full_grid group of the paper networks' brackets)
def test_the_full_grid_estimate_brackets_the_measured_peak() -> None:
    """A recipe at SemanticKITTI's full grid: measured at 64x64x8 and 128x128x16, the range holds the peak of a
    real step at 256x256x32 (batch 1). The tiny SCPNet at 2 channels (the grid is what is extrapolated; its two
    dense steps at 256x256x32 are nearly all of the test's time, half of it at 4 channels; peak 1.6 GiB)."""
    recipe = tiny_recipe(steps=1)
    recipe["data"]["params"].update(scale=1)
    recipe["stages"]["teacher"]["model"]["params"].update(channels=2, seg_channels=2)
    res = resolve(recipe_from_dict(recipe), "full")
    est = memory.estimate_stage(res, "teacher")
    assert est is not None and est.size == "a 256x256x32 grid" and est.low < est.high
    truth = memory.measure_step(res, "teacher", res.data_params.model_copy(update={"num_train": 1})).total
    # to 1 % (a nearly dense network: the bounds meet, and the figure is printed to 0.1 GiB)
    assert 0.99 * est.low <= truth <= 1.01 * est.high, (est.low, truth, est.high)


@pytest.mark.slow
def test_a_real_out_of_memory_under_a_memory_limit_is_one_line(tmp_path: Path) -> None:
    """SCPNet with 64 channels on a 128x128x16 grid, in a process limited to 4 GiB of address space."""
    import resource
    import subprocess
    import sys

    recipe = tiny_recipe(steps=2, distill=False)
    recipe["data"]["params"].update(scale=2)
    recipe["stages"]["teacher"]["model"]["params"].update(channels=64)
    recipe["stages"]["teacher"]["train"]["batch_size"] = 2
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(recipe))

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))

    done = subprocess.run([sys.executable, "-m", "distilkit", "run", str(path), "-o", str(tmp_path / "runs"), "-q"],
                          capture_output=True, text=True, preexec_fn=limit, timeout=600)
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.startswith("error: stage 'teacher' ran out of memory") and "Traceback" not in done.stderr
    assert done.stderr.count("\n") == 1


@pytest.mark.slow
def test_the_paper_size_full_grid_recipe_gets_a_memory_warning(tmp_path: Path, capsys, monkeypatch) -> None:
    """recipes/scpnet_dskd.yaml at SemanticKITTI's full grid with the paper's SCPNet (channels 32, point MLP
    64-128-256-256, batch 2), validated on a machine with 24 GB: the warning names the figure and what to lower."""
    recipe = yaml.safe_load((Path(__file__).resolve().parents[1] / "recipes" / "scpnet_dskd.yaml").read_text())
    recipe["data"]["params"].update(scale=1, num_train=2, num_val=1, num_test=1)
    recipe["stages"] = {"teacher": recipe["stages"]["teacher"]}
    recipe["stages"]["teacher"]["model"]["params"].update(channels=32, point_mlp=[64, 128, 256, 256])
    recipe["stages"]["teacher"]["train"]["batch_size"] = 2
    path = tmp_path / "full.yaml"
    path.write_text(yaml.safe_dump(recipe))
    monkeypatch.setattr(memory, "available_memory", lambda device: 24 * GIB)
    assert main(["validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert "a 256x256x32 grid; extrapolated from 32,768 and 262,144 voxels" in out
    assert "warning: stage teacher may need up to" in out and "lower train.batch_size (now 2)" in out
