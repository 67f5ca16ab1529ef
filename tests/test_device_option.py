"""``--device``: the tests' device (cpu by default). ``python -m pytest --device cuda`` on a machine without CUDA stops
at once with one line saying so (status 4), instead of failing test after test."""

from __future__ import annotations

import os
import subprocess
import sys

import torch

from conftest import ROOT


def test_device_cuda_without_cuda_stops_with_one_line() -> None:
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}  # no GPU to see, on any machine
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", "--device", "cuda",
                           "tests/test_sparse.py"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]
    assert done.returncode == 4, done.stdout + done.stderr
    assert len(lines) == 1 and "--device cuda: CUDA is not available on this machine" in lines[0], lines


def test_the_device_fixture_is_the_option(device, pytestconfig) -> None:
    assert device == torch.device(pytestconfig.getoption("--device"))
    assert torch.zeros(1, device=device).device.type == device.type
