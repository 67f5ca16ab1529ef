"""End to end: the README's quickstart through the CLI, then again (every stage reused)."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from conftest import ROOT


@pytest.mark.slow
def test_quickstart_runs_and_reuses(tmp_path) -> None:
    cmd = [sys.executable, "-m", "distilkit", "run", str(ROOT / "recipes" / "quickstart.yaml"), "-o", str(tmp_path)]
    first = subprocess.run(cmd, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "student + DSKD" in first.stdout and "mIoU" in first.stdout
    t0 = time.perf_counter()
    second = subprocess.run(cmd, capture_output=True, text=True)
    assert second.returncode == 0 and second.stdout.count("reused from") == 3
    assert time.perf_counter() - t0 < 60
    assert (tmp_path / "quickstart" / "report.md").is_file()
