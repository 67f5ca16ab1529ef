"""scripts/gpu-check stays runnable between GPU visits and within its budget: its dry run on the CPU
(``--device cpu --quick``: the same sections, smaller) writes every section of the report with results and leaves
nothing in the temporary folder; a section that hangs is stopped at its deadline and the check still ends within its
budget; on a machine without CUDA the real check stops at once with one line saying so."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "gpu-check"


def test_without_cuda_the_gpu_check_stops_with_one_line(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "r.md")], capture_output=True,
                          text=True, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""}, timeout=120)
    assert done.returncode == 4 and "CUDA is not available on this machine" in done.stderr
    assert not (tmp_path / "r.md").exists()


def test_a_section_that_hangs_is_stopped_and_the_check_keeps_its_budget(tmp_path: Path) -> None:
    out, tmp = tmp_path / "r.md", tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "TMPDIR": str(tmp), "DISTILKIT_GPU_CHECK_SLEEP": "bf16:600"}
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--quick", "--budget", "15", "--out",
                           str(out), "--sections", "bf16", "benchmarks"], capture_output=True, text=True, env=env,
                          timeout=120)
    seconds = time.monotonic() - t0
    assert done.returncode == 0, done.stdout + done.stderr
    assert seconds <= 15 + 10, seconds  # the budget, and the check's own start and end
    report = out.read_text()
    bf16, benchmarks = report.split("## bf16 against fp32")[1].split("## benchmarks")
    assert "**stopped: the time budget ran out during it**" in bf16, report
    assert "**not run: the time budget ran out before it.**" in benchmarks or "exit status 0" in benchmarks, report
    assert "it ran out of time" in report.splitlines()[-1], report
    assert not list(tmp.iterdir())  # the check's folder removed, the sleeping section's process group killed


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
    assert "the same bits" in report  # two deterministic runs of the same recipe
    rows = [line for line in report.splitlines() if line.startswith("| ") and " % |" in line]
    assert len(rows) == 5 and all(float(r.split("|")[4].strip(" %")) < 5.0 for r in rows), rows  # bf16 vs fp32
    assert report.count("| yes |") == 3, report  # each estimate brackets its measured peak
    assert "Finished in" in report and "ran out of time" not in report
    assert seconds <= 8 * 60, seconds  # the dry run's budget on a 2-core machine
    assert not list(tmp.iterdir())  # every temporary folder removed
