"""Bad input and faults a new user hit (issue 27, items 11-16): one line (exit 2) instead of a traceback, nothing
silently accepted, messages that name the right thing, runs that stop with their parent."""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from _camera_kitti import camera_kitti
from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import FIXTURES, folder_recipe, process_context, tiny_recipe
from distilkit.cli import main
from distilkit.data.pointfiles import read_points
from distilkit.errors import DataError

SCAN = FIXTURES / "semantickitti-sample" / "sequences" / "00" / "velodyne" / "000000.bin"


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """This process's exported SemanticKITTI folder (tests/_camera_kitti.py), read only: the tests that break files
    work on a copy."""
    return camera_kitti(tmp_path_factory)


def copy_of(exported: Path, tmp_path: Path) -> Path:
    root = tmp_path / "k"
    shutil.copytree(exported, root)
    return root


def dataset(root: Path, **params):
    from distilkit.registry import DATASETS

    entry = DATASETS.entry("semantickitti")
    return entry.obj(entry.meta["params"](root=str(root), train=["00"], val=None, **params), "train")


def test_poses_that_are_short_or_malformed_are_named(exported, tmp_path) -> None:
    root = copy_of(exported, tmp_path)
    poses = root / "sequences" / "00" / "poses.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join(lines[:3]) + "\n")
    with pytest.raises(DataError, match=r"poses.txt: 3 poses for the 11 scans"):
        dataset(root, input_frames=2)[0]
    poses.write_text("\n".join([lines[0], "1 2 three 4 5 6 7 8 9 10 11 12", *lines[2:]]) + "\n")
    with pytest.raises(DataError, match=r"poses.txt:2: a pose line must be 12 numbers"):
        dataset(root, input_frames=2)[0]


def test_non_finite_and_empty_scans_follow_one_rule_and_a_deleted_voxel_label_is_said(exported, tmp_path) -> None:
    root = copy_of(exported, tmp_path)
    scan = root / "sequences" / "00" / "velodyne" / "000000.bin"
    pts = np.fromfile(scan, "<f4").reshape(-1, 4)
    pts[3, 1] = np.nan
    pts.tofile(scan)
    with pytest.raises(DataError, match=r"000000.bin: 1 of \d+ points have non-finite coordinates"):
        dataset(root)[0]
    with pytest.raises(DataError, match=r"1 of \d+ points have non-finite coordinates"):
        read_points(scan)  # what `distilkit complete` reads: the same rule, the same words
    scan.write_bytes(b"")
    (root / "sequences" / "00" / "labels" / "000000.label").unlink()
    with pytest.raises(DataError, match=r"velodyne/000000.bin: the scan holds no point"):
        dataset(root)[0]
    root2 = copy_of(exported, tmp_path / "b")
    (root2 / "sequences" / "00" / "voxels" / "000005.label").unlink()
    ds = dataset(root2)
    assert len(ds) == 2 and any("000005" in n and "no voxels/*.label" in n for n in ds.notes)


def test_a_read_only_output_folder_is_one_line_and_a_finished_run_still_prints_its_table(tmp_path, capsys,
                                                                                         monkeypatch) -> None:
    """A read-only folder, as a user without write access sees it (simulated: the tests may run as root, whom
    permissions do not stop): every write there fails with PermissionError."""
    import distilkit.files

    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(tiny_recipe(steps=1, distill=False)))
    out = tmp_path / "runs"
    assert main(["run", str(path), "-o", str(out), "-q"]) == 0
    capsys.readouterr()

    def denied(p: object) -> OSError:
        return PermissionError(13, "Permission denied", str(p))

    inside = lambda p: str(p).startswith(str(out))  # noqa: E731
    real_access, real_mkdir, real_write = os.access, Path.mkdir, distilkit.files.atomic_write
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if inside(p) and mode & os.W_OK
                        else real_access(p, mode, *a, **k))

    def mkdir(self, *a, **k):
        if inside(self) and not self.is_dir():
            raise denied(self)
        return real_mkdir(self, *a, **k)

    def atomic_write(p, write):
        if inside(p):
            raise denied(p)
        return real_write(p, write)

    monkeypatch.setattr(Path, "mkdir", mkdir)
    monkeypatch.setattr(distilkit.files, "atomic_write", atomic_write)
    assert main(["run", str(path), "-o", str(out)]) == 0  # finished: read, reported, nothing written
    text = capsys.readouterr().out
    assert "distilkit results" in text and "read-only" in text
    path.write_text(yaml.safe_dump(tiny_recipe(steps=2, distill=False)))  # a stage that must be trained there
    assert main(["run", str(path), "-o", str(out), "-q"]) == 2
    assert "permission denied" in capsys.readouterr().err.lower()


def test_complete_refuses_bad_numbers_and_names_malformed_ply_headers(tmp_path, capsys) -> None:
    for args, words in ((["--steps", "0"], "--steps 0: must be at least 1"),
                        (["--steps", "-3"], "--steps -3: must be at least 1"),
                        (["--scan-points", "-5"], "--scan-points -5: must be at least 1"),
                        (["--scan-points", "0"], "--scan-points 0: must be at least 1"),
                        (["--guidance", "nan"], "--guidance nan: must be a finite number")):
        assert main(["complete", str(tmp_path / "nowhere"), str(SCAN), "--out", str(tmp_path / "o.ply"), *args]) == 2
        assert words in capsys.readouterr().err
    header = "ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
    for n, words in (("abc", "the vertex count must be a whole number"), ("-5", "the vertex count must be a whole")):
        (tmp_path / "a.ply").write_text(header.format(n=n) + "end_header\n1 2 3\n")
        with pytest.raises(DataError, match=words):
            read_points(tmp_path / "a.ply")
    (tmp_path / "b.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float\nend_header\n1\n")
    with pytest.raises(DataError, match="expected 'property TYPE NAME'"):
        read_points(tmp_path / "b.ply")


def test_predict_and_checkpoint_messages_name_the_right_thing(exported, tmp_path, capsys) -> None:
    import torch

    np.save(tmp_path / "scan.npy", np.zeros((5, 3), np.float32))
    assert main(["predict", str(tmp_path / "scan.npy"), "--dataset-root", str(exported), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "None" not in err and "not a readable checkpoint" in err
    recipe = folder_recipe(exported, train=["00"], val=["08"], scale=4)
    (path := tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    assert main(["run", str(path), "-o", str(tmp_path / "runs"), "-q"]) == 0
    run = next((tmp_path / "runs" / "kitti").glob("scpnet-*"))
    assert main(["predict", str(run), "--dataset-root", str(tmp_path / "missing"), "--split", "valid",
                 "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err
    assert "--split valid" in err and "split 'test'" not in err

    class Payload:
        def __reduce__(self):
            return (os.system, ("echo never",))

    torch.save({"student": Payload()}, tmp_path / "evil.pt")
    assert main(["predict", str(tmp_path / "evil.pt"), "--dataset-root", str(exported), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "never runs code from a file" in err and "weights_only" not in err and "will likely succeed" not in err


def _children(pid: int) -> list[int]:
    """Processes whose parent is ``pid`` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = (Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _sweep(folder: Path) -> None:
    """`distilkit sweep --jobs 2` of ``folder``'s sweep, in a process forked from this one (its own process, which
    the test signals; it need not import torch and distilkit again, ~4 s; spawned on a machine with a GPU): its output to ``folder/sweep.log``."""
    import torch

    os.chdir(folder)
    os.environ["OMP_NUM_THREADS"] = "1"  # its runs'
    torch.set_num_threads(1)  # its own: GNU OpenMP in a forked child hangs on more once its parent has used them
    log = os.open(folder / "sweep.log", os.O_WRONLY | os.O_CREAT)
    os.dup2(log, 1)
    os.dup2(log, 2)
    sys.exit(main(["sweep", str(folder / "sweep.yaml"), "--jobs", "2", "-o", str(folder / "runs"), "-q"]))


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the sweep's runs through /proc (Linux)")
@pytest.mark.parametrize("how", ["SIGTERM", "SIGKILL"])
def test_a_stopped_sweep_leaves_no_run_training(tmp_path, how: str) -> None:
    """SIGTERM to `distilkit sweep --jobs 2` stops its runs (their checkpoints written); SIGKILL leaves them
    orphaned, and they notice and stop on their own. Over 3 s: a sweep process and its two run processes, trained
    until signalled, are its point (the sweep is forked from this process, its runs are `distilkit run` processes
    as a user's sweep starts them)."""
    recipe = tiny_recipe(steps=2000, distill=False)
    recipe["stages"]["teacher"]["train"].update(eval_every=2000, checkpoint_every=1000)
    (tmp_path / "base.yaml").write_text(yaml.safe_dump(recipe))
    (tmp_path / "sweep.yaml").write_text(yaml.safe_dump({
        "schema_version": 1, "name": "orphans", "recipe": "base.yaml", "stage": "teacher", "seeds": [0, 1],
        "variants": {"a": {"label": "a"}}}))
    proc = process_context().Process(target=_sweep, args=(tmp_path,))  # spawned on a GPU machine
    proc.start()
    deadline = time.time() + 120
    runs: list[int] = []
    while time.time() < deadline and len(runs) < 2:
        runs = _children(proc.pid)
        time.sleep(0.2)
    assert len(runs) == 2, "the sweep did not start its two runs"

    def training() -> int:  # runs that logged a step: they are in their training loop (no fixed sleep)
        return sum('"loss"' in p.read_text() for p in (tmp_path / "runs").rglob("metrics.jsonl"))

    while time.time() < deadline and training() < 2 and proc.is_alive():
        time.sleep(0.05)
    assert training() == 2, "the sweep's two runs did not start training"
    os.kill(proc.pid, signal.SIGTERM if how == "SIGTERM" else signal.SIGKILL)
    proc.join(timeout=120)
    assert proc.exitcode is not None, "the sweep did not end"
    deadline = time.time() + 60
    while time.time() < deadline and any(_alive(p) for p in runs):
        time.sleep(0.2)
    assert not any(_alive(p) for p in runs), f"runs left training after {how}"
    logs = "".join(p.read_text() for p in (tmp_path / "runs").rglob("metrics.jsonl"))
    assert logs.count('"event": "stopped"') == 2  # each wrote its checkpoint at the step it stopped
