"""``distilkit complete``: point files in and out, and a trained LiDiff completing a real scan."""

from __future__ import annotations

import numpy as np
import pytest

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import FIXTURES
from distilkit.cli import main
from distilkit.data.pointfiles import read_points, write_points
from distilkit.engine.train.pipeline import Pipeline
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


@pytest.fixture(scope="module")
def lidiff_runs(tmp_path_factory):
    """A LiDiff teacher, an evaluate-only copy of it at 1 sampler step (teacher_1), a refiner of teacher_1's
    completions and an evaluate-only refiner of the teacher's (refined_2), trained once for the tests that complete
    scans with them (read only). The stages train on the CPU: the tests are about `distilkit complete` (which runs
    on the CPU), not training."""
    data = {"num_train": 2, "num_val": 1, "num_test": 1, "scan_points": 32, "scene_points": 128, "frames": 3,
            "beams": 8, "azimuth_steps": 128}
    train = {"steps": 1, "batch_size": 2, "eval_every": 1, "metric": "cd", "device": "cpu"}
    recipe = {"schema_version": 1, "name": "r", "seed": 0, "data": {"dataset": "synthetic-scenes", "params": data},
              "stages": {"teacher": {"model": {"adapter": "lidiff", "params": {"channels": 8, "blocks": 1,
                                                                                "duplicate": 4, "sample_steps": 2}},
                                     "train": train},
                         "teacher_1": {"model": {"adapter": "lidiff", "params": {"channels": 8, "blocks": 1,
                                                                                  "duplicate": 4, "sample_steps": 1}},
                                       "init": {"from": "teacher", "strict": False}, "train": {**train, "steps": 0}},
                         "refiner": {"model": {"adapter": "lidiff-refine", "params": {"channels": 8}},
                                     "aux": {"diffusion": {"from": "teacher_1", "inputs": {"completion": "coarse"}}},
                                     "train": train},
                         "refined_2": {"model": {"adapter": "lidiff-refine", "params": {"channels": 8}},
                                       "aux": {"diffusion": {"from": "teacher", "inputs": {"completion": "coarse"}}},
                                       "init": {"from": "refiner"}, "train": {**train, "steps": 0}}}}
    return Pipeline(recipe_from_dict(recipe), tmp_path_factory.mktemp("lidiff") / "runs", quiet=True).run()


@pytest.mark.xdist_group("complete_lidiff")  # one worker trains the shared stages once
def test_a_trained_lidiff_completes_a_real_scan_from_the_command_line(lidiff_runs, tmp_path, capsys) -> None:
    result = lidiff_runs[0]  # the teacher
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


def _kitti_scan(n: int, seed: int = 0) -> np.ndarray:
    """An (n, 4) float32 scan in SemanticKITTI's layout (x, y, z, remission) the size of an HDL-64E sweep: ground
    rings and two walls around the sensor, 1.73 m above the road."""
    rng = np.random.default_rng(seed)
    k = n // 2
    r, a = rng.uniform(3.0, 60.0, k), rng.uniform(-np.pi, np.pi, k)
    ground = np.stack([r * np.cos(a), r * np.sin(a), np.full(k, -1.73) + rng.normal(0, 0.02, k)], 1)
    x = rng.uniform(-40, 40, n - k)
    wall = np.stack([x, np.where(rng.random(n - k) < 0.5, -6.0, 7.0), rng.uniform(-1.7, 3.0, n - k)], 1)
    xyz = np.concatenate([ground, wall]).astype(np.float32)
    return np.concatenate([xyz, rng.uniform(0, 1, (n, 1)).astype(np.float32)], 1)


@pytest.mark.xdist_group("complete_lidiff")  # one worker trains the shared stages once
def test_complete_refine_on_a_kitti_format_scan_of_125k_points(lidiff_runs, tmp_path, capsys) -> None:
    """`distilkit complete --refine`: the LiDiff completion of a full-size scan, refined to six points per point
    (time and memory of LiDiff's sizes: `distilkit bench complete`)."""
    # an evaluate-only stage (teacher_1: the teacher's weights at 1 step) serves as an auxiliary model, and an
    # evaluate-only refiner scores the refinement of another model's completions
    teacher, _, refiner, refined_2 = lidiff_runs
    assert refiner.summary["test"]["best"]["cd"] > 0 and refined_2.summary["test"]["best"]["cd"] > 0
    assert refined_2.summary["test"]["best"]["cd"] != refiner.summary["test"]["best"]["cd"]
    scan = tmp_path / "000000.bin"
    _kitti_scan(125_000).tofile(scan)
    assert len(read_points(scan)) == 125_000
    plain, refined = tmp_path / "plain.npy", tmp_path / "refined.npy"
    assert main(["complete", str(teacher.run_dir), str(scan), "--out", str(plain), "--seed", "1"]) == 0
    assert main(["complete", str(teacher.run_dir), str(scan), "--out", str(refined), "--seed", "1",
                 "--refine", str(refiner.run_dir)]) == 0
    coarse, fine = read_points(plain), read_points(refined)
    assert 0 < len(coarse) <= 4 * 32 and len(fine) == 6 * len(coarse)  # the same completion, six offsets per point
    moved = np.linalg.norm(fine.reshape(-1, 6, 3) - coarse[:, None], axis=2)
    assert (moved <= np.sqrt(3) + 1e-5).all()  # tanh offsets: at most 1 m per axis
    assert "refined" in capsys.readouterr().out
    assert main(["complete", str(teacher.run_dir), str(scan), "--out", str(refined), "--refine",
                 str(teacher.run_dir)]) == 2
    assert "cannot refine a completion" in capsys.readouterr().err
