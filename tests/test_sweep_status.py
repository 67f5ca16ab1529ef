"""`distilkit sweep FILE --status` for a sweep run on this machine: each run's state read from its folder (done,
running under a held stage lock, stopped with a checkpoint, waiting), the pace of the finished runs, the grid."""

from __future__ import annotations

import json
import threading
from pathlib import Path

from distilkit.cli import main
from distilkit.engine.store.lock import stage_lock
from distilkit.sweep.local_status import RunState, pace, run_info, run_state, summary_line
from test_sweep import write_sweep


def _folder(root: Path, name: str, summary: dict | None = None, checkpoint: bool = False) -> Path:
    run = root / name
    (run / "checkpoints").mkdir(parents=True)
    if summary is not None:
        (run / "summary.json").write_text(json.dumps(summary))
    if checkpoint:
        (run / "checkpoints" / "last.pt").write_bytes(b"state")
    return run


def test_each_state_is_read_from_the_folder(tmp_path: Path) -> None:
    done = _folder(tmp_path, "kd-1", {"status": "finished", "finished_at": "2026-11-29T03:00:00"})
    assert run_state(done)[0] == "done" and run_state(done)[1] is not None
    timed = _folder(tmp_path, "kd-0", {"status": "finished", "finished_at": "2026-11-29T03:00:00", "train_seconds": 51.5})
    assert run_info(timed)[2] == 51.5 and run_info(done)[2] is None and run_info(tmp_path / "kd-9")[2] is None
    assert run_state(_folder(tmp_path, "kd-2", checkpoint=True)) == ("stopped", None)
    assert run_state(_folder(tmp_path, "kd-3", {"status": "running"})) == ("waiting", None)
    running = _folder(tmp_path, "kd-4", checkpoint=True)
    held, release = threading.Event(), threading.Event()

    def hold() -> None:  # another holder of the stage lock: flock is per open file, so a thread stands in for it
        with stage_lock(tmp_path / ".locks" / "kd-4.lock"):
            held.set()
            release.wait(10)

    t = threading.Thread(target=hold)
    t.start()
    try:
        assert held.wait(10)
        assert run_state(running) == ("running", None)
    finally:
        release.set()
        t.join()
    assert run_state(running) == ("stopped", None)  # the holder is gone: the lock is free again


def test_the_pace_is_the_wall_clock_per_run_of_the_last_ends() -> None:
    assert pace([100.0]) is None and pace([]) is None
    assert pace([0.0, 60.0, 120.0, 180.0]) == 60.0
    assert pace([0.0, 1000.0, 1060.0, 1120.0], last=3) == 60.0  # only the last three ends
    # a stop between two ends (the sweep stopped an hour): the gap counts at most 1.5x the run that ends it
    ends, took = [0.0, 60.0, 3660.0, 3720.0], [50.0, 50.0, 40.0, 50.0]
    assert pace(ends) == 1240.0 and pace(ends, seconds=took) == (60.0 + 60.0 + 60.0) / 3
    assert pace(list(reversed(ends)), seconds=list(reversed(took))) == 60.0  # each end keeps its own run's time
    assert pace([0.0, 60.0, 120.0], seconds=[None, None, 10.0]) == (60.0 + 15.0) / 2  # a run without its time
    found = [RunState("kd", s, "done", 60.0 * s) for s in range(4)] + [RunState("kd", 4, "running"),
                                                                          RunState("kd", 5, "waiting")]
    line = summary_line("sw", found, now=200.0)
    assert line.startswith("sweep sw: 4 of 6 runs done, 1 running, 0 stopped")
    assert "about 2 min more at the pace of the last 4 (60 s a run)" in line and "ago" not in line
    idle = summary_line("sw", [r for r in found if r.state != "running"], now=180.0 + 3600)
    assert "once the sweep runs again" in idle and "the last run ended 1 h 00 min ago" in idle


def test_status_of_a_local_sweep_prints_the_grid_and_trains_nothing(tmp_path: Path, capsys) -> None:
    path = write_sweep(tmp_path, seeds=[0, 1])
    out = tmp_path / "runs"
    assert main(["sweep", str(path), "-o", str(out), "-q", "--seeds", "0"]) == 0
    capsys.readouterr()
    before = sorted(p.name for p in (out / "sw").iterdir())
    assert main(["sweep", str(path), "-o", str(out), "--status"]) == 0
    printed = capsys.readouterr().out
    assert "sweep sw: 2 of 4 runs done, 0 running, 0 stopped" in printed
    rows = {ln.split("│")[1].strip(): [c.strip() for c in ln.split("│")[2:-1]] for ln in printed.splitlines()
            if ln.startswith("│")}
    assert rows == {"none": ["✓", "·", "1/2"], "dskd": ["✓", "·", "1/2"]}, printed
    assert sorted(p.name for p in (out / "sw").iterdir()) == before  # nothing trained, nothing written
