"""scripts/gpu-check stays runnable between GPU visits and within its budget: its dry run on the CPU
(``--device cpu --quick``: the same sections, smaller) writes every section of the report with results and leaves
nothing in the temporary folder; a section that hangs is stopped at its deadline and the check still ends within its
budget; on a machine without CUDA the real check stops at once with one line saying so."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType

import pytest

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "gpu-check"


def gpu_check_module() -> ModuleType:
    """scripts/gpu-check imported as a module (a file without ``.py``), to call its ``main`` in this process."""
    loader = importlib.machinery.SourceFileLoader("gpu_check_script", str(SCRIPT))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    return module


def test_without_cuda_the_gpu_check_stops_with_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    """The real check (``--device cuda``, the default) where torch sees no CUDA: exit status 4, one line on stderr
    saying so, no report (in this process, torch.cuda.is_available answering False)."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    code = gpu_check_module().main(["--out", str(tmp_path / "r.md")])
    err = capsys.readouterr().err
    assert code == 4 and "CUDA is not available on this machine" in err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r.md").exists()


BUDGET = 7  # seconds: the machine section (which fails at once here: under 0.5 s at a load of 12 on 2 cores) and
# the bf16 section's 5 s minimum fit in it, with 2 s to spare


def test_a_section_that_hangs_is_stopped_and_the_check_keeps_its_budget(tmp_path: Path) -> None:
    """The bf16 section sleeps 600 s before it works: it is stopped when the budget runs out, the benchmarks after
    it are not run, the check still returns within its budget (plus its own start and end), says that it ran out of
    time, and its temporary folder is removed (the sleeping section's process group killed). The sections see a
    ``torch`` that cannot be imported (a stand-in first on PYTHONPATH), so that the report's machine lines fail at
    once instead of taking a loaded machine's torch import out of the budget (the bf16 section sleeps before it
    imports anything). It takes the budget's 7 s of wall time (asleep, not computing): waiting the budget out is
    its point."""
    out, tmp, stub = tmp_path / "r.md", tmp_path / "tmp", tmp_path / "no-torch"
    tmp.mkdir()
    stub.mkdir()
    (stub / "torch.py").write_text("raise ImportError('no torch in this test')\n")
    path = os.pathsep.join([str(stub), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
    env = {**os.environ, "TMPDIR": str(tmp), "DISTILKIT_GPU_CHECK_SLEEP": "bf16:600", "PYTHONPATH": path}
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--quick", "--budget", str(BUDGET),
                           "--out", str(out), "--sections", "bf16", "benchmarks"], capture_output=True, text=True,
                          env=env, timeout=120)
    seconds = time.monotonic() - t0
    assert done.returncode == 0, done.stdout + done.stderr
    assert seconds <= BUDGET + 10, seconds  # the budget, and the check's own start and end
    report = out.read_text()
    bf16, benchmarks = report.split("## bf16 against fp32")[1].split("## benchmarks")
    assert "**stopped: the time budget ran out during it**" in bf16, report
    assert "**not run: the time budget ran out before it.**" in benchmarks or "exit status 0" in benchmarks, report
    assert "it ran out of time" in report.splitlines()[-1], report
    assert not list(tmp.iterdir())  # the check's folder removed, the sleeping section's process group killed


def test_the_benchmarks_section_times_a_step_within_its_time_and_bf16_runs_at_the_papers_sizes_on_cuda(
        tmp_path: Path, monkeypatch) -> None:
    """The section's commands: the other benchmarks, then ``distilkit bench step`` at the papers' sizes on CUDA
    (its rows in STEP_ONLY's order: the recipes' distillation steps first) with a time limit that ends it before the
    section's time does, at the reduced sizes in the dry run (VoxFormer's teacher, the cheapest row there); and the
    bf16 section's trainers at the full grid on CUDA, the reduced one in the dry run."""
    check = gpu_check_module()
    cuda, dry = check.parse(["--device", "cuda"]), check.parse(["--device", "cpu", "--quick"])
    assert "step" in check.BENCHMARKS and cuda.bench is None
    assert check.bench_command(cuda, ["dskd", "relation", "sparse"]) == [
        "bench", "--device", "cuda", "dskd", "relation", "sparse"]
    step = check.step_command(cuda, 120.0)
    assert step[:4] == ["bench", "--device", "cuda", "step"] and "--quick" not in step
    limit = float(step[step.index("--time-limit") + 1])
    assert 0 < limit <= 120.0 - check.STEP_MARGIN
    only = step[step.index("--only") + 1:]
    assert only[:2] == ["recipe*fp32", "recipe*bf16"] and any(p.startswith("teacher") for p in only)
    step = check.step_command(dry, 60.0)
    assert step[:5] == ["bench", "--device", "cpu", "--quick", "step"]
    assert step[step.index("--only") + 1:] == ["VoxFormer teacher fp32"]
    assert check.step_command(dry, 5.0)[6] == "1"  # never a limit below a second
    seen = []
    import types

    import distilkit.engine.memory.probe

    monkeypatch.setattr(check, "resolved", lambda name, root, quick, extra: seen.append((name, quick, extra))
                        or types.SimpleNamespace(data_params=None))
    monkeypatch.setattr(distilkit.engine.memory.probe, "probe_trainer", lambda *a, **k: "trainer")
    monkeypatch.setattr("distilkit.data.probe._one_scene", lambda params: params)
    for args, quick in ((cuda, False), (dry, True)):
        seen.clear()
        check.bf16_trainer(args, tmp_path, "scpnet", "student_dskd", "bf16")
        assert seen == [("scpnet", quick, ["stages.*.train.batch_size=1", f"stages.*.train.device={args.device}",
                                           "stages.student_dskd.train.precision=bf16"])]
    assert "data.params.scale=8" not in check.paper_sets("scpnet", tmp_path, False)  # the full grid
    assert "data.params.scale=8" in check.paper_sets("scpnet", tmp_path, True)


@pytest.mark.slow
def test_the_gpu_check_dry_run_writes_every_section(tmp_path: Path) -> None:
    out, tmp = tmp_path / "gpu-report.md", tmp_path / "tmp"
    tmp.mkdir()
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--quick", "--out", str(out)],
                          capture_output=True, text=True, env={**os.environ, "TMPDIR": str(tmp)}, timeout=900)
    seconds = time.monotonic() - t0
    assert done.returncode == 0, done.stdout + done.stderr
    report = out.read_text()
    for section in ("## tests", "## benchmarks", "## determinism", "## bf16 against fp32",
                    "## memory estimate against the measured peak"):
        assert section in report, section
    assert "**failed" not in report and "not run" not in report and "stopped" not in report, report
    assert re.search(r"exit status 0: [1-9]\d* passed, 0 failed", report), report  # the device-fixture tests
    assert "sparse: SubMConv3d vs dense conv3d" in report
    # distilkit bench step at the reduced sizes: VoxFormer's teacher measured, the same on spconv said to be moot
    assert "`distilkit bench --device cpu --quick step --time-limit " in report
    assert "--only 'VoxFormer teacher fp32'`: exit status 0" in report
    step = report.split("--only 'VoxFormer teacher fp32'`", 1)[1].split("## determinism")[0]
    assert "step: VoxFormer teacher" in step and "fp32, torch; batch 1, 184x610 image, 128x128x16" in " ".join(
        step.split())
    assert all(column in step for column in ("reserved", "syncs", "GPU busy", "fp16 scale"))
    assert "top ops by self CPU time: " in step
    assert "The first training step's loss of each paper network at the reduced 32 x 32 x 4 grid" in report
    assert "the same bits" in report  # two deterministic runs of the same recipe
    rows = [line for line in report.splitlines() if line.startswith("| ") and " % |" in line]
    assert len(rows) == 5 and all(float(r.split("|")[4].strip(" %")) < 5.0 for r in rows), rows  # bf16 vs fp32
    assert report.count("| yes |") == 3, report  # each estimate brackets its measured peak
    assert "Finished in" in report and "ran out of time" not in report
    assert seconds <= 8 * 60, seconds  # the dry run's budget on a 2-core machine
    assert not list(tmp.iterdir())  # every temporary folder removed
