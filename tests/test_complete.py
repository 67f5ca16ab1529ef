"""``distilkit complete``: point files in and out, and a trained LiDiff completing a real scan."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import FIXTURES
from distilkit.cli import main
from distilkit.data.pointfiles import read_points, write_points
from distilkit.engine.pipeline import Pipeline
from distilkit.errors import DataError
from distilkit.recipe import recipe_from_dict

SCAN = FIXTURES / "semantickitti-sample" / "sequences" / "00" / "velodyne" / "000000.bin"


def test_point_files_round_trip_and_malformed_files_are_named(tmp_path) -> None:
    pts = np.random.default_rng(0).normal(size=(20, 3)).astype(np.float32)
    for suffix in (".ply", ".npy", ".bin"):
        assert np.array_equal(read_points(write_points(tmp_path / f"a{suffix}", pts)), pts)
    ascii_ply = tmp_path / "b.ply"
    ascii_ply.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                         "property float z\nproperty uchar red\nend_header\n1 2 3 255\n4 5 6 0\n")
    assert read_points(ascii_ply).tolist() == [[1, 2, 3], [4, 5, 6]]
    raw = np.fromfile(SCAN, dtype="<f4").reshape(-1, 4)
    assert np.array_equal(read_points(SCAN), raw[:, :3])
    bad = tmp_path / "cut.bin"
    bad.write_bytes(SCAN.read_bytes()[:-3])
    with pytest.raises(DataError, match="cut.bin: 797 bytes is not a whole number"):
        read_points(bad)
    (tmp_path / "c.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n")
    with pytest.raises(DataError, match="no x, y, z properties"):
        read_points(tmp_path / "c.ply")
    with pytest.raises(DataError, match="unknown point-cloud format '.txt'"):
        (tmp_path / "d.txt").write_text("1 2 3")
        read_points(tmp_path / "d.txt")


def test_a_trained_lidiff_completes_a_real_scan_from_the_command_line(tmp_path, capsys) -> None:
    data = {"num_train": 2, "num_val": 1, "num_test": 1, "scan_points": 32, "scene_points": 128, "frames": 3,
            "beams": 8, "azimuth_steps": 128}
    recipe = {"schema_version": 1, "name": "c", "seed": 0, "data": {"dataset": "synthetic-scenes", "params": data},
              "stages": {"teacher": {"model": {"adapter": "lidiff", "params": {"channels": 8, "blocks": 1,
                                                                                "duplicate": 4, "sample_steps": 2}},
                                     "train": {"steps": 1, "batch_size": 2, "eval_every": 1, "metric": "cd"}}}}
    (result,) = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    out = tmp_path / "scene.ply"
    assert main(["complete", str(result.run_dir), str(SCAN), "--out", str(out), "--steps", "3"]) == 0
    scene = read_points(out)
    assert 0 < len(scene) <= 4 * 32  # the scan sampled to the trained 32 points, duplicated 4 times, post-processed
    assert (np.linalg.norm(scene[:, :2], axis=1) < 50).all()
    assert "in 3 steps" in capsys.readouterr().out
    broken = tmp_path / "broken.bin"
    broken.write_bytes(b"\0" * 10)
    assert main(["complete", str(result.run_dir), str(broken), "--out", str(tmp_path / "x.ply")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "broken.bin" in err and "16 bytes" in err
