"""``distilkit bench step`` (issue 56): its rows built and run at the tests' sizes (``step_cases(..., test=True)``:
32 x 32 x 4, a 16-beam scan, 24 x 80 images) on the device of ``--device`` — a paper network (VoxFormer's, the
cheapest here: a few seconds a row on a CPU) as a student and as a teacher, a student's fp16 step through a
GradScaler, and Scribble2Scene's distillation step as its trainer takes it — each with sane figures (time, peak
memory, host syncs, the profiled step's top ops; on CUDA the GPU-busy fraction); what cannot run (a missing backend,
one that refuses the call, a network without sparse convolutions on a library) is a line with its reason; ``--only``
orders the rows and ``--time-limit`` names those it left; and the host-sync counter the bench and
tests/test_sparse_syncs.py share counts a known sync and not a sync-free op."""

from __future__ import annotations

import functools
import math
from typing import Iterator

import pytest
import torch

from distilkit.bench import measure, step as bench_step
from distilkit.bench.syncs import host_syncs


@pytest.fixture(scope="module", autouse=True)
def _released() -> Iterator[None]:
    """The bench keeps the last subject it built resident: released when this module's tests end."""
    yield
    bench_step.release()


def rows(device: torch.device, *patterns: str) -> dict[str, bench_step.Case]:
    """The test-size rows whose objective and size match one of ``patterns``, by ``objective | size``."""
    from distilkit.bench.runner import selected

    cases = [c for c in bench_step.step_cases(device, quick=True, test=True) if c.skipped is None]
    return {f"{c.objective} | {c.size}": c for c in selected(cases, list(patterns))}


def one(device: torch.device, pattern: str) -> bench_step.Case:
    found = rows(device, pattern)
    assert len(found) == 1, list(found)
    return next(iter(found.values()))


def check_figures(case: bench_step.Case, device: torch.device) -> dict:
    ms, peak, value = case.measure()
    figures = case.figures  # type: ignore[attr-defined]
    assert ms > 0 and len(figures["times"]) == measure.TIMED and ms == sorted(figures["times"])[2]
    assert peak is not None and peak > 0 and math.isfinite(value)
    assert isinstance(figures["syncs"], int) and figures["syncs"] >= 0
    assert figures["top"] and all(name and t >= 0 and n >= 1 and 0 <= share <= 1
                                  for name, t, n, share in figures["top"])
    if device.type == "cuda":  # kernels over the median step; reserved at least what was allocated
        assert 0 < figures["busy"] <= 1.5 and figures["reserved"] >= peak
    else:
        assert figures["busy"] is None and figures["reserved"] is None and case.columns["reserved"] == "n/a"
    assert case.columns["syncs"] == str(figures["syncs"])
    note = case.note({})  # the profile's line under the table
    assert figures["top"][0][0][:20] in note and ("top kernels" if device.type == "cuda" else "self CPU") in note
    return figures


def test_the_sync_counter_counts_an_item_and_not_a_sync_free_op(device) -> None:
    x = torch.arange(6.0, device=device)
    with host_syncs(device) as syncs:
        y = (x * 2 + 1).sum()
    assert syncs == []
    with host_syncs(device) as syncs:
        y.item()
    assert len(syncs) >= 1, syncs
    if device.type == "cpu":
        assert syncs == ["aten._local_scalar_dense.default"]


def test_busy_time_is_the_union_of_kernel_spans_and_the_top_ranks_by_total_time() -> None:
    # two overlapping kernels (0-10 and 5-15 us) and one apart (20-30): 25 us busy, not 30
    assert measure.busy_ms([(20, 30), (0, 10), (5, 15)]) == pytest.approx(0.025)
    top = measure.top_by_time([("a", 100.0, 1), ("b", 300.0, 3), ("a", 250.0, 2), ("c", 50.0, 1)], n=2)
    assert [(name, n) for name, _, n, _ in top] == [("a", 3), ("b", 3)]
    assert top[0][1] == pytest.approx(0.35) and top[0][3] == pytest.approx(350 / 700)


def test_a_paper_network_as_a_student_and_as_a_teacher(device) -> None:
    student = one(device, "VoxFormer student fp32, torch")
    assert "batch 1" in student.size  # recipes/paper/scribble2scene.yaml's student stage
    figures = check_figures(student, device)
    assert student.columns["fp16 scale"] == "—"
    teacher = one(device, "VoxFormer teacher fp32, torch")
    taught = check_figures(teacher, device)
    assert taught["value"] == 0.0  # a forward only: no loss
    if device.type == "cpu":  # the forward alone holds less than forward, backward and Adam's state
        assert taught["peak"] < figures["peak"]


def test_an_fp16_step_scales_its_loss_with_a_grad_scaler(device) -> None:
    """A student's fp16 row takes its steps through a GradScaler and records its scale (on LiDiff's refiner at
    ``size: tiny``: a paper network's fp16 step costs 20 s of a CPU's emulated half precision)."""
    from distilkit.bench.fixtures import network_cases

    network = next(c for c in network_cases(True, True, sizes=("tiny",)) if c.family == "LiDiff refine")
    case = bench_step.row("step: LiDiff refine (tiny) student", "fp16, torch", device, "torch",
                          lambda: bench_step.network_subject(network, "student", 1, device, "fp16"))
    figures = check_figures(case, device)
    assert isinstance(figures["scaler"], torch.amp.GradScaler) and figures["scaler"].is_enabled()
    assert figures["scale"] is not None and figures["scale"] > 0
    assert case.columns["fp16 scale"] == f"{figures['scale']:,.0f}"


def test_a_paper_recipes_distillation_step_runs_as_its_trainer_takes_it(device) -> None:
    case = one(device, "recipe scribble2scene student fp32, torch")
    assert "rgo2d + weighted_ce + geo_scal" in case.size and "batch 1" in case.size
    figures = check_figures(case, device)
    assert figures["value"] > 0  # the stage's loss: its CE, geo_scal and RGO²D
    assert case.columns["fp16 scale"] == "—"


def test_what_cannot_run_is_a_line_with_its_reason(device, monkeypatch, capsys) -> None:
    """spconv-triton made present here and refusing bf16 autocast: one line for the bf16 steps it refuses, no such
    row; VoxFormer's teacher (no sparse convolution) on a library is a line too, and its torch row runs and prints
    the bench's columns and its profile's note."""
    from distilkit.bench import BENCHES, run_bench
    from distilkit.sparse import backend

    real_problem, real_refusal = backend.problem, backend.refusal
    monkeypatch.setattr(backend, "problem", lambda name, dev: None if name == "spconv-triton"
                        else real_problem(name, dev))
    monkeypatch.setattr(backend, "refusal", lambda name, call: (
        ("bfloat16 autocast: refused in this test" if call.autocast and call.dtype == torch.bfloat16 else None)
        if name == "spconv-triton" else real_refusal(name, call)))
    cases = bench_step.step_cases(device, quick=True, test=True)
    lines = {(c.objective, c.size): c.skipped for c in cases if c.skipped}
    assert lines[("step: spconv-triton backend", "bf16 students' and recipes' steps")] == \
        "bfloat16 autocast: refused in this test"
    assert not any("bf16, spconv-triton" in c.size for c in cases if not c.skipped)
    assert any("fp32, spconv-triton" in c.size for c in cases if not c.skipped)
    monkeypatch.setitem(BENCHES, "step", functools.partial(bench_step.step_cases, test=True))
    done = run_bench(["step"], device=device.type, only=["VoxFormer teacher fp32"])
    out = capsys.readouterr().out
    assert [r["size"].split(";")[0] for r in done] == ["fp32, torch"]
    assert set(done[0]["columns"]) == {"reserved", "syncs", "GPU busy", "fp16 scale"}
    for column in ("reserved", "syncs", "GPU busy", "fp16 scale"):
        assert column in out
    assert "naive ms" not in out  # no row compares two forms
    assert "step: spconv-triton backend (bf16 students' and recipes' steps): skipped — bfloat16 autocast: " \
           "refused in this test" in out
    assert "step: VoxFormer teacher (fp32, spconv-triton; batch 1" in out
    assert "skipped — it holds no sparse convolution" in out
    assert "top ops by self CPU time" in out or "top kernels" in out


def test_only_runs_the_rows_in_its_patterns_order_and_the_time_limit_names_those_left(capsys) -> None:
    from distilkit.bench import run_bench
    from distilkit.errors import DistilkitError

    done = run_bench(["step"], quick=True, only=["recipe*fp16, torch", "JS3C-Net teacher bf16, torch"], time_limit=0)
    out = " ".join(capsys.readouterr().out.split())
    assert done == []
    left = out.split("the time limit of 0 s was reached before they started: ", 1)[1]
    order = ["step: recipe js3cnet student_dskd (fp16, torch", "step: recipe scorelidar student (fp16, torch",
             "step: recipe scpnet student_dskd (fp16, torch", "step: recipe scribble2scene student (fp16, torch",
             "step: JS3C-Net teacher (bf16, torch"]  # the first pattern's rows first, each in the bench's order
    where = [left.find(name) for name in order]
    assert -1 not in where and where == sorted(where), (where, left)
    assert left.count("step: ") == len(order)
    with pytest.raises(DistilkitError, match="no case of step matches"):
        run_bench(["step"], quick=True, only=["no such row"])
