"""`distilkit validate` finds what the run would stop on at its first step (issue 44): every registered objective
between a mismatched student and teacher (a camera student and a LiDAR teacher, taps of other widths) is a problem —
exit 2, one line naming the stage, the term, the error and the shapes it read, no traceback, never "ok" beside a
"memory not estimated (...Error...)" — and a stage's sparse convolutions that cannot run where it runs (spconv
missing; spconv's CPU build asked for a backward) are a problem with the line the run stops with."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import ROOT, TINY_DATA
from distilkit.cli import main
from distilkit.registry import OBJECTIVES

TRAIN = {"steps": 1, "batch_size": 1, "device": "cpu"}
LIDAR = {"adapter": "scpnet", "params": {"channels": 4, "point_mlp": [8], "seg_channels": 4, "frames": 2}}
CAMERA = {"adapter": "voxformer", "params": {"geometry": "ground-truth"}}
# a teacher tap of the voxel_logits kind 4 wide (the completion sub-network's output) where the student has 20 classes
NARROW = {"narrow": {"module": "net.completion", "kind": "voxel_logits"}}
FEATURES = {"student": "image_features", "teacher": "completion_dense"}  # (B, C, H, W) against (B, C, X, Y, Z)
LOGITS = {"student": "logits", "teacher": "narrow"}

# objective -> (recipe, the objective's entry): "dry" pairs fail on their first step (validate runs it); "lidar" and
# "scenes" ones are refused before any model runs (the recipe's taps or the teacher's methods do not fit)
MISMATCHED = {
    "cleaners": ("dry", {"taps": {"student_features": "image_features", "teacher_features": "completion_dense"}}),
    "fitnets": ("dry", {"taps": FEATURES}),
    "l2cocc_fsd": ("dry", {"taps": FEATURES}),
    "l2cocc_relation": ("dry", {"taps": FEATURES}),
    "mgd": ("dry", {"taps": FEATURES}),
    "nst": ("dry", {"taps": FEATURES}),
    "rgo2d": ("dry", {"taps": {"student_features": "image_features", "teacher_features": "completion_dense",
                                "labels": "voxel_target"}}),
    "dist": ("dry", {"taps": LOGITS}),
    "hassc_kd": ("dry", {"taps": LOGITS}),
    "kd": ("dry", {"taps": LOGITS}),
    "l2cocc_pad": ("dry", {"taps": LOGITS}),
    "pvkd": ("dry", {"taps": {"student": "query_features", "teacher": "completion", "student_logits": "logits",
                               "teacher_logits": "narrow"}}),
    "hassc_hvm": ("lidar", {}),  # a camera student has no volume features for its head
    "licrocc_kl": ("dry", {"taps": LOGITS}),
    # a camera student has no bird's-eye tap (nor, here, the teacher: its tap named is a volume, refused on its own
    # line), nor a volume for MonoOcc's KL; the LiDAR teacher has no image features for MonoOcc's image term
    "licrocc_bev": ("lidar", {"taps": {"teacher": "completion_dense"}}),
    "licrocc_affinity": ("lidar", {"taps": {"teacher": "completion_dense"}}),
    "bev_from_voxels": ("lidar", {}),
    "monoocc_kl": ("lidar", {}),
    "monoocc_image": ("lidar", {}),
    "vsd": ("scenes", {}),  # a teacher without predict_noise (LiDiff's refinement network)
    "distillation_dpo": ("scenes", {}),
}
NO_MISMATCH = {
    "dskd": "relational (voxel-by-voxel cosine matrices): any widths; the grids of any two adapters on one data set "
            "tile each other (the camera's queries at half the LiDAR grid), and grids that do not tile are refused "
            "by resolve already",
    "pkt": "cosine-kernel distributions over sampled voxels: any widths, and the same grids as dskd",
    "structural": "reads the student's points and the ground truth only: no teacher tap to mismatch",
}


def test_every_registered_objective_has_a_mismatch_or_a_reason() -> None:
    assert set(MISMATCHED) | set(NO_MISMATCH) == set(OBJECTIVES.names())
    assert not set(MISMATCHED) & set(NO_MISMATCH)


def _recipe(group: str, objectives: list[str]) -> dict:
    if group == "scenes":
        data = {"dataset": "synthetic-scenes", "params": {"num_train": 1, "num_val": 1, "num_test": 1, "scan_points": 200,
                                                          "scene_points": 2000, "frames": 3, "beams": 16,
                                                          "azimuth_steps": 256}}
        lidiff = {"adapter": "lidiff", "params": {"channels": 8, "blocks": 1, "sample_steps": 2, "generate_steps": 1}}
        stages = {"diff": {"model": lidiff, "train": TRAIN},
                  "refine": {"model": {"adapter": "lidiff-refine", "params": {"channels": 8}},
                             "aux": {"coarse": {"from": "diff"}}, "train": TRAIN}}
        stages.update({f"s_{o}": {"model": lidiff, "teacher": {"from": "refine"}, "distill": [{"name": o}],
                                  "train": TRAIN} for o in objectives})
    else:
        data = {"dataset": "synthetic-lidar", "params": {**TINY_DATA, "num_train": 1, "camera": {"height": 24,
                                                                                                 "width": 80}}}
        stages = {"lidar": {"model": LIDAR, "train": TRAIN}}
        stages.update({f"s_{o}": {"model": CAMERA, "teacher": {"from": "lidar", "taps": NARROW},
                                  "distill": [{"name": o, **MISMATCHED[o][1]}], "train": TRAIN} for o in objectives})
    return {"schema_version": 1, "name": f"mismatched_{group}", "seed": 0, "data": data, "stages": stages}


def _validate(path: Path, *extra: str) -> tuple[int, str, str]:
    """validate in this process: an exception that escapes main() (a traceback) fails the test."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["validate", str(path), *extra])
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def validated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[int, str, str]]:
    """Each recipe of mismatched pairs validated once (one stage per objective), by recipe."""
    folder = tmp_path_factory.mktemp("mismatched")
    out = {}
    for group in ("dry", "lidar", "scenes"):
        path = folder / f"{group}.yaml"
        path.write_text(yaml.safe_dump(_recipe(group, [o for o, (g, _) in MISMATCHED.items() if g == group])))
        out[group] = _validate(path, "--no-memory")
    return out


@pytest.mark.xdist_group("mismatched")  # one worker validates the three recipes once for every objective
@pytest.mark.parametrize("objective", sorted(MISMATCHED))
def test_validate_refuses_each_objective_between_a_mismatched_pair(objective, validated) -> None:
    group = MISMATCHED[objective][0]
    code, out, err = validated[group]
    assert code == 2 and "ok" not in out and "Traceback" not in err, (code, out, err)
    lines = [line.strip() for line in err.splitlines() if f"stages.s_{objective}.distill[0]:" in line]
    assert len(lines) == 1, err  # the stage and the term, one line
    if group == "dry":  # failed on its first step: the term, the error, and the shapes of both taps it read
        line = lines[0]
        assert f"objective '{objective}' fails on its first step" in line, line
        assert "it read student" in line and "teacher" in line.split("it read", 1)[1], line
        assert "(1, 4, 32, 32, 4)" in line, line  # the teacher's map (completion_dense or the narrow logits)


def test_a_term_that_fails_with_the_memory_estimate_on_is_a_problem_never_a_note(tmp_path) -> None:
    """The issue's case: l2cocc_relation between a camera student and a LiDAR teacher; with the memory estimate
    (the default) the estimate's first step finds it — exit 2, no "ok", no "memory not estimated"."""
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(_recipe("dry", ["l2cocc_relation"])))
    code, out, err = _validate(path)
    assert code == 2 and "ok" not in out and "memory not estimated" not in out + err, (out, err)
    assert "stages.s_l2cocc_relation.distill[0]: objective 'l2cocc_relation' fails on its first step" in err, err
    assert "(1, 16, 6, 20)" in err and "(1, 4, 32, 32, 4)" in err, err  # both shapes


def test_static_runs_no_model_and_says_what_it_did_not_check(tmp_path) -> None:
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(_recipe("dry", ["l2cocc_relation"])))
    code, out, err = _validate(path, "--static")
    assert code == 0 and "terms not run on a dry batch (--static)" in out + err, (out, err)


# -- sparse convolutions that cannot run where the stage runs -------------------------------------------------------

@pytest.fixture(scope="module")
def paper_sparse(tmp_path_factory: pytest.TempPathFactory) -> list[str]:
    """A paper recipe on sparse convolutions on an exported folder, one CPU step per stage: its arguments.
    JS3C-Net's release network cut to 2 levels of width 4 (SCPNet's, fixed at its size, took ten times the CPU for
    the same lines)."""
    from _camera_kitti import camera_kitti
    from test_paper_recipes import overrides

    folder = camera_kitti(tmp_path_factory)  # this process's exported folder (read only), as tests/test_sparse_backends
    sets = overrides("js3cnet", folder, small=True) + [
        "stages.*.train.steps=1", "stages.*.train.epochs=null", "stages.*.train.batch_size=1",
        "stages.*.train.device=cpu", "stages.*.model.params.levels=2", "stages.*.model.params.seg_channels=4",
        "stages.*.model.params.ssc_channels=4"]
    return [str(ROOT / "recipes" / "paper" / "js3cnet.yaml"), "--set", *sets]


def _error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err
    return lines[0]


def test_validate_refuses_a_sparse_backend_that_is_not_installed_with_the_runs_line(paper_sparse, tmp_path) -> None:
    """DISTILKIT_SPARSE=spconv with spconv unimportable (a fresh process): validate exits 2 with the line the run
    stops with at step 0 (was: "sparse convolutions: cannot run — ..." and exit 0). Over 3 s: the fresh process
    (Python, torch and distilkit started without spconv) is its point."""
    code = ("import sys; sys.modules['spconv'] = None\n"
            "from distilkit.cli import main\n"
            f"args = {paper_sparse!r}\n"
            "print('VALIDATE', main(['validate', '--no-memory', args[0], *args[1:]]), flush=True)\n"
            f"print('RUN', main(['run', args[0], '-q', '-o', {str(tmp_path / 'runs')!r}, '--stage', 'teacher', "
            "*args[1:]]), flush=True)\n")
    env = {**os.environ, "DISTILKIT_SPARSE": "spconv"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT)
    assert "VALIDATE 2" in done.stdout and "RUN 2" in done.stdout, (done.stdout, done.stderr)
    assert "Traceback" not in done.stderr, done.stderr
    validate_err, run_err = done.stderr.split("error:", 2)[1:]  # validate's error, then the run's
    run_line = run_err.strip().splitlines()[0]
    assert run_line.startswith("sparse backend spconv (DISTILKIT_SPARSE) on the cpu: spconv does not import"), run_err
    assert "stages teacher, student, student_dskd: " + run_line in validate_err, (validate_err, run_line)


def test_validate_refuses_spconvs_cpu_build_for_a_training_stage(paper_sparse, tmp_path, monkeypatch,
                                                                  capsys) -> None:
    """spconv's CPU build computes the forward only: a CPU training stage is refused by validate with the run's own
    line ("computes the forward only"); a stage that only evaluates is not."""
    from test_sparse_backends import spconv_or_skip

    spconv_or_skip()
    monkeypatch.setenv("DISTILKIT_SPARSE", "spconv")
    assert main(["validate", "--no-memory", *paper_sparse]) == 2
    validate_line = _error_line(capsys.readouterr().err)
    assert "computes the forward only" in validate_line and "stages teacher, student, student_dskd" in validate_line
    assert main(["run", paper_sparse[0], "-q", "-o", str(tmp_path / "runs"), "--stage", "teacher",
                 *paper_sparse[1:]]) == 2
    run_line = _error_line(capsys.readouterr().err)
    assert run_line.removeprefix("error: ") in validate_line, (validate_line, run_line)
    assert main(["validate", "--no-memory", *paper_sparse, "stages.*.train.steps=0"]) == 0  # evaluation: a forward
    assert "sparse convolutions on the cpu: spconv (DISTILKIT_SPARSE=spconv)" in capsys.readouterr().out
