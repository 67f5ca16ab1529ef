"""scripts/gpu-check stays runnable between GPU visits: its dry run on the CPU (``--device cpu --quick``, a few tests
and benchmarks) writes every section of the report with results, and on a machine without CUDA the real check
stops at once with one line saying so."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

SCRIPT = ROOT / "scripts" / "gpu-check"


def test_without_cuda_the_gpu_check_stops_with_one_line(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "--out", str(tmp_path / "r.md")], capture_output=True,
                          text=True, env={**os.environ, "CUDA_VISIBLE_DEVICES": ""}, timeout=120)
    assert done.returncode == 4 and "CUDA is not available on this machine" in done.stderr
    assert not (tmp_path / "r.md").exists()


@pytest.mark.slow
def test_the_gpu_check_dry_run_writes_every_section(tmp_path: Path) -> None:
    out = tmp_path / "gpu-report.md"
    done = subprocess.run([sys.executable, str(SCRIPT), "--device", "cpu", "--quick", "--out", str(out),
                           "--budget", "1500", "--tests", "tests/test_device_option.py", "--bench", "dskd", "sparse"],
                          capture_output=True, text=True, timeout=1800)
    assert done.returncode == 0, done.stdout + done.stderr
    report = out.read_text()
    for section in ("## tests", "## benchmarks", "## determinism", "## bf16 against fp32",
                    "## memory estimate against the measured peak"):
        assert section in report, section
    assert "failed:" not in report and "not run" not in report and "stopped" not in report, report
    assert "2 passed" in report and "sparse: SubMConv3d vs dense conv3d" in report
    assert "the same bits" in report  # two deterministic runs of the same recipe
    rows = [line for line in report.splitlines() if line.startswith("| ") and " % |" in line]
    assert len(rows) == 5 and all(float(r.split("|")[4].strip(" %")) < 5.0 for r in rows), rows  # bf16 vs fp32
    assert report.count("| yes |") == 3, report  # each estimate brackets its measured peak
    assert "Finished in" in report and "ran out of time" not in report
