"""`distilkit init` for every family pair of the built-in adapters (LiDAR <-> LiDAR, LiDAR <-> camera, a ground-truth
voxel teacher, points -> points, and the pairs it must refuse) and a plug-in: what `--yes` writes (the objectives,
their taps, the auxiliary stages), that the file validates, that one trains, `--show`, `--static`, the numbered
questions on stdin, and the rules behind the choices on hand-made taps (no model)."""

from __future__ import annotations

import contextlib
import io
import re
import sys
from pathlib import Path

import pytest
import yaml

from conftest import ROOT, TINY_DATA
from distilkit.cli import main

pytestmark = pytest.mark.xdist_group("init")  # one worker: torch and the data cached once for every row

SCPNET = ["channels=4", "point_mlp=[8]", "seg_channels=4"]
JS3CNET = ["seg_channels=4", "embed=4", "ssc_channels=4", "pvi_hidden=4", "knn=4"]
LIDIFF = ["channels=8", "blocks=1", "sample_steps=2"]
LIDAR_DATA = [f"{k}={v}" for k, v in TINY_DATA.items()] + ["num_train=1"]
CAMERA_DATA = LIDAR_DATA + ["camera={height: 24, width: 80}"]
SCENES_DATA = ["num_train=1", "num_val=1", "num_test=1", "scan_points=200", "scene_points=2000", "frames=3",
               "beams=16", "azimuth_steps=256"]


def init(*argv: str) -> tuple[int, str, str]:
    """`distilkit init` in this process: an exception that escapes main() (a traceback) fails the test."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["init", *argv])
    return code, out.getvalue(), err.getvalue()


def args(teacher: str, t_params: list[str], student: str, s_params: list[str], data: list[str]) -> list[str]:
    out = ["--teacher", teacher, "--student", student, "--data-params", *data]
    if t_params:
        out += ["--teacher-params", *t_params]
    if s_params:
        out += ["--student-params", *s_params]
    return out


# row -> (teacher, its params, student, its params, data params, the distill stage's [(objective, taps)], stages)
ROWS = {
    "lidar-one-net": ("scpnet", SCPNET + ["frames=2"], "scpnet", SCPNET + ["frames=1"], LIDAR_DATA,
                      [("kd", {"student": "logits", "teacher": "logits"}),
                       ("dskd", {"student": "completion", "teacher": "completion"})], {"teacher", "student"}),
    "js3cnet-to-scpnet": ("js3cnet", JS3CNET, "scpnet", SCPNET, LIDAR_DATA,
                          [("kd", {"student": "logits", "teacher": "logits"}),
                           ("dskd", {"student": "completion", "teacher": "completion"})], {"teacher", "student"}),
    "scpnet-to-js3cnet": ("scpnet", SCPNET, "js3cnet", JS3CNET, LIDAR_DATA,
                          [("kd", {"student": "logits", "teacher": "logits"}),
                           ("dskd", {"student": "completion", "teacher": "completion"})], {"teacher", "student"}),
    "lidar-to-camera": ("scpnet", SCPNET, "voxformer", [], CAMERA_DATA,
                        [("kd", {"student": "logits", "teacher": "logits"}),
                         ("dskd", {"student": "query_features", "teacher": "completion"})],
                        {"proposal", "teacher", "student"}),
    "camera-to-lidar": ("voxformer", ["geometry=ground-truth"], "scpnet", SCPNET, CAMERA_DATA,
                        [("kd", {"student": "logits", "teacher": "logits"}),
                         ("dskd", {"student": "completion", "teacher": "query_features"})], {"teacher", "student"}),
    "camera-to-camera": ("voxformer", ["geometry=ground-truth"], "voxformer", ["geometry=ground-truth"],
                         CAMERA_DATA, [("kd", {"student": "logits", "teacher": "logits"}),
                                       ("dskd", {"student": "query_features", "teacher": "query_features"})],
                         {"teacher", "student"}),
    "ground-truth-voxels-to-lidar": ("dean-labeler", [], "scpnet", SCPNET, LIDAR_DATA,
                                     [("kd", {"student": "logits", "teacher": "logits"}),
                                      ("fitnets", {"student": "completion_dense", "teacher": "features"})],
                                     {"teacher", "student"}),
    "points-to-points": ("lidiff", LIDIFF, "lidiff", LIDIFF + ["generate_steps=1"], SCENES_DATA,
                         [("vsd", {"student": "samples"})], {"teacher"}),
}


def distill_stage(recipe: dict) -> tuple[str, dict]:
    [(name, stage)] = [(n, s) for n, s in recipe["stages"].items() if "distill" in s]
    return name, stage


@pytest.mark.parametrize("row", sorted(ROWS))
def test_yes_writes_the_expected_recipe_and_it_validates(row, tmp_path) -> None:
    teacher, tp, student, sp, data, want, stages = ROWS[row]
    out = tmp_path / "pair.yaml"
    code, stdout, err = init(*args(teacher, tp, student, sp, data), "--yes", "-o", str(out))
    assert code == 0, err
    assert "validated" in stdout
    recipe = yaml.safe_load(out.read_text())
    name, stage = distill_stage(recipe)
    assert [(t["name"], t["taps"]) for t in stage["distill"]] == want
    assert stage["teacher"] == {"from": "teacher"} and stage["model"]["adapter"] == student
    assert {n for n in recipe["stages"] if n != name} == stages
    assert recipe["stages"]["teacher"]["model"]["adapter"] == teacher
    text = out.read_text()
    assert text.startswith("# written by: distilkit init") and "# pairs" in text
    for term in stage["distill"]:  # each term says which taps it pairs, or what it reads
        line = next(line for line in text.splitlines() if f"name: {term['name']}," in line)
        assert row == "points-to-points" or "  # " in line, line


def test_the_camera_student_gets_its_proposal_stage_and_the_data_its_camera(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    assert init(*args("scpnet", SCPNET, "voxformer", [], LIDAR_DATA), "--yes", "-o", str(out))[0] == 0
    recipe = yaml.safe_load(out.read_text())
    assert recipe["data"]["params"]["camera"] == {}  # the adapter's DATA_PARAMS
    assert recipe["stages"]["proposal"]["model"]["adapter"] == "voxformer-proposal"
    for name in ("student", "student_kd_dskd"):
        assert recipe["stages"][name]["aux"] == {"proposal": {"from": "proposal"}}


def test_a_written_recipe_trains_and_validates_with_validate(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    assert init(*args("js3cnet", JS3CNET, "scpnet", SCPNET, LIDAR_DATA), "--yes", "-o", str(out),
                "--set", "stages.*.train.steps=1", "stages.*.train.batch_size=1")[0] == 0
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["validate", str(out), "--no-memory"]) == 0
        assert main(["run", str(out), "-q", "--output", str(tmp_path / "runs")]) == 0
    summaries = sorted((tmp_path / "runs").rglob("summary.json"))
    assert len(summaries) == 3 and all('"finished"' in p.read_text() for p in summaries)


def test_a_student_without_its_default_task_loss_taps_gets_none_and_no_baseline(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    teacher, tp, student, sp, data, _, _ = ROWS["points-to-points"]
    assert init(*args(teacher, tp, student, sp, data), "--yes", "-o", str(out))[0] == 0
    recipe = yaml.safe_load(out.read_text())
    assert recipe["stages"]["student_vsd"]["task_losses"] == [] and "student" not in recipe["stages"]
    assert recipe["stages"]["student_vsd"]["init"] == {"from": "teacher", "strict": False}  # ScoreLiDAR's start
    assert "no task loss: lidiff (the student's default) reads eps, eps_pred" in out.read_text()


def test_pairs_it_must_refuse_exit_2_with_the_reasons(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    # a refinement network has no predict_noise for score distillation; the data gives no voxel labels for kd
    code, _, err = init(*args("lidiff-refine", [], "lidiff", LIDIFF + ["generate_steps=1"], SCENES_DATA), "--yes",
                        "-o", str(out))
    assert code == 2 and "predict_noise()" in err and "'lidiff-refine' lacks" in err and not out.exists()
    code, _, err = init(*args("lidiff-refine", [], "lidiff", LIDIFF + ["generate_steps=1"], SCENES_DATA), "--yes",
                        "--objectives", "structural", "-o", str(out))
    assert code == 0, err
    recipe = yaml.safe_load(out.read_text())
    assert recipe["stages"]["teacher"]["aux"] == {"coarse": {"from": "coarse"}}  # the refiner reads a completion
    assert recipe["stages"]["coarse"]["model"]["adapter"] == "lidiff"
    # no dataset gives both a scan/scene and LiDAR points
    code, _, err = init("--teacher", "lidiff", "--student", "scpnet", "--yes", "-o", str(out), "--force")
    assert code == 2 and "no registered dataset serves both models" in err
    assert "synthetic-scenes lacks what the student 'scpnet' reads point_batch" in err and "Traceback" not in err


def test_a_plug_in_student_is_paired_by_its_declared_taps(tmp_path, monkeypatch) -> None:
    from distilkit.registry import ADAPTERS

    before, imported = set(ADAPTERS.names()), "tiny_adapter" in sys.modules
    monkeypatch.syspath_prepend(str(ROOT / "docs" / "examples" / "tiny_adapter"))
    import tiny_adapter

    tiny_adapter.register()
    try:
        out = tmp_path / "pair.yaml"
        code, _, err = init(*args("scpnet", SCPNET, "tiny-ssc", [], LIDAR_DATA), "--yes", "-o", str(out))
        assert code == 0, err
        _, stage = distill_stage(yaml.safe_load(out.read_text()))
        assert [(t["name"], t["taps"]) for t in stage["distill"]] == [
            ("kd", {"student": "logits", "teacher": "logits"}), ("dskd", {"student": "features",
                                                                          "teacher": "completion"})]
    finally:
        for name in set(ADAPTERS.names()) - before:
            ADAPTERS.remove(name)
        if not imported:
            sys.modules.pop("tiny_adapter", None)


def test_show_lists_taps_pairs_and_why_an_objective_does_not_fit(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    code, out, _ = init(*args("scpnet", SCPNET, "voxformer", [], CAMERA_DATA), "--show")
    assert code == 0 and not list(tmp_path.iterdir())  # writes nothing
    text = " ".join(out.split())
    assert "query_features" in text and "teacher finer x2" in text and "16 <- 4" in text  # probed widths
    assert "◆ dskd" in text and "◆ kd" in text
    assert "the teacher 'scpnet' has no image_features tap" in " ".join(text.replace("│", " ").split())


def test_static_runs_no_model_and_gives_equal_width_terms_a_connector(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    code, stdout, err = init(*args("dean-labeler", [], "scpnet", SCPNET, LIDAR_DATA), "--static", "--yes",
                             "--objectives", "kd,monoocc_kl", "-o", str(out))
    assert code == 0, err
    assert "--static: no term ran" in stdout
    _, stage = distill_stage(yaml.safe_load(out.read_text()))
    kd, mono = stage["distill"]
    assert "connector" not in kd  # the logits' width is the classes': known without a forward
    assert mono["connector"] == "linear" and mono["taps"] == {"student": "completion_dense", "teacher": "features"}
    assert "channels: ?" not in out.read_text() and ", ? ch," in out.read_text()


def test_the_numbered_questions_read_stdin(tmp_path, monkeypatch) -> None:
    from distilkit.registry import ADAPTERS

    out = tmp_path / "asked.yaml"
    adapters = ADAPTERS.names()
    answers = [str(adapters.index("scpnet") + 1), str(adapters.index("scpnet") + 1), "synthetic-lidar",
               "", "each", "n", str(out)]
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n".join(answers) + "\n"))
    code, _, err = init("--interactive", "--teacher-params", *SCPNET, "frames=2", "--student-params", *SCPNET,
                        "--data-params", *LIDAR_DATA)
    assert code == 0, err
    recipe = yaml.safe_load(out.read_text())
    assert set(recipe["stages"]) == {"teacher", "student_kd", "student_dskd"}  # one stage each, no baseline


def test_the_data_question_numbers_only_the_datasets_that_serve_both(tmp_path, monkeypatch) -> None:
    """A dataset that cannot serve the pair is listed dimmed with its reason, not numbered: `1` is the first that
    can (the tiny parameters leave only the synthetic streets; a folder dataset needs its root)."""
    from distilkit.registry import ADAPTERS

    out = tmp_path / "asked.yaml"
    scpnet = str(ADAPTERS.names().index("scpnet") + 1)
    monkeypatch.setattr(sys, "stdin", io.StringIO("\n".join([scpnet, scpnet, "1", "", "combined", "n", str(out)])
                                                  + "\n"))
    code, stdout, err = init("--interactive", "--teacher-params", *SCPNET, "frames=2", "--student-params", *SCPNET,
                             "--data-params", *LIDAR_DATA)
    assert code == 0, err
    offered = re.search(r"data: 0\) the first that serves both(.*)", stdout)
    assert offered and offered.group(1).split("  ")[1:] == ["1) synthetic-lidar"], stdout
    assert "not offered: semantickitti needs root (--data-params)" in stdout
    assert "not offered: synthetic-scenes: scale: Extra inputs" in stdout  # the tiny LiDAR parameters are not its
    assert yaml.safe_load(out.read_text())["data"]["dataset"] == "synthetic-lidar"


def test_taps_put_an_objective_on_the_pair_named(tmp_path) -> None:
    """`--taps`: FitNets on the camera students' bird's-eye maps of their query features (which init makes, and
    offers to the terms that read bird's-eye maps only, unless named) instead of its best pair (the image maps), the
    pair checked by the same rules; a pair it cannot read, a role it lacks and a malformed item are one-line
    errors."""
    camera = ("voxformer", ["geometry=ground-truth"], "voxformer", ["geometry=ground-truth"], CAMERA_DATA)
    out = tmp_path / "forced.yaml"
    code, _, err = init(*args(*camera), "--taps", "fitnets.student=bev_query_features",
                        "fitnets.teacher=bev_query_features", "--yes", "-o", str(out))
    assert code == 0, err
    _, stage = distill_stage(yaml.safe_load(out.read_text()))
    assert [(t["name"], t["taps"]) for t in stage["distill"]] == \
        [("fitnets", {"student": "bev_query_features", "teacher": "bev_query_features"})]
    assert stage["model"]["taps"]["bev_query_features"]["of"] == "query_features"  # the map init makes
    code, _, err = init(*args(*camera), "--objectives", "kd", "--taps", "fitnets.student=bev_query_features",
                        "fitnets.teacher=bev_query_features", "--yes",
                        "-o", str(tmp_path / "both.yaml"))
    assert code == 0, err
    _, stage = distill_stage(yaml.safe_load((tmp_path / "both.yaml").read_text()))
    assert [t["name"] for t in stage["distill"]] == ["kd", "fitnets"]
    assert stage["distill"][1]["taps"] == {"student": "bev_query_features", "teacher": "bev_query_features"}
    code, _, err = init(*args(*camera), "--taps", "fitnets.teacher=bev_query_features", "--yes",
                        "-o", str(tmp_path / "x.yaml"))  # the student's made map is not named: not offered
    assert code == 2 and "fitnets: --taps: teacher=bev_query_features is a bird's-eye map init makes: name the " \
        "student side's tap too" in err
    code, _, err = init(*args(*camera), "--taps", "cleaners.student_features=image_features",
                        "cleaners.teacher_features=image_features", "--yes", "-o", str(tmp_path / "opt.yaml"))
    assert code == 0, err  # optional roles, read because they are named
    _, stage = distill_stage(yaml.safe_load((tmp_path / "opt.yaml").read_text()))
    assert stage["distill"][0]["taps"] == {"student": "logits", "teacher": "logits",
                                           "student_features": "image_features", "teacher_features": "image_features"}
    code, _, err = init(*args(*camera), "--taps", "fitnets.student=image_feature", "--yes",
                        "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "--taps: student=image_feature: no tap of the student that aligns" in err
    assert "image_features" in err  # the taps it could have named
    code, _, err = init(*args(*camera), "--taps", "rgo2d.labels=voxel_target", "--yes", "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "--taps rgo2d.labels: labels is a field of the batch, not a model's tap" in err
    code, _, err = init(*args(*camera), "--taps", "fitnets.student=logits", "fitnets.teacher=image_features",
                        "--yes", "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "fitnets: --taps: student=logits: a voxel_logits tap, and student reads a feature_map tap" \
        in err
    lidar = args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA)
    code, _, err = init(*lidar, "--taps", "hassc_hvm.features=completion_dense", "--yes", "-o", str(tmp_path / "h.yaml"))
    assert code == 0, err  # a role only the student fills, named
    _, stage = distill_stage(yaml.safe_load((tmp_path / "h.yaml").read_text()))
    assert stage["distill"][0]["taps"]["features"] == "completion_dense"
    code, _, err = init(*lidar, "--taps", "hassc_hvm.features=logits", "--yes", "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "--taps: features reads a student volume_features tap, and 'logits' is not one" in err
    code, _, err = init(*args(*camera), "--taps", "fitnets.foo=logits", "--yes", "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "fitnets reads no role 'foo' (its roles: student, teacher)" in err
    code, _, err = init(*args(*camera), "--taps", "fitnets=logits", "--yes", "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "expected OBJECTIVE.ROLE=TAP" in err
    assert not (tmp_path / "x.yaml").exists()


def test_mistakes_are_named(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    out.write_text("mine\n")
    code, _, err = init(*args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA), "--yes", "-o", str(out))
    assert code == 2 and "exists" in err and "--force" in err and out.read_text() == "mine\n"
    code, _, err = init("--teacher", "scpent", "--student", "scpnet", "--yes")
    assert code == 2 and "did you mean 'scpnet'" in err
    code, _, err = init(*args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA), "--objectives", "vsd", "--yes",
                        "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "vsd: the data lacks condition" in err
    code, _, err = init("--teacher", "scpnet", "--yes")
    assert code == 2 and "give --teacher and --student" in err


# the rules, on hand-made taps


def _facts(role, taps):
    from distilkit.pairing.facts import ModelFacts

    return ModelFacts(role, "x", {}, None, frozenset(), taps)


def test_tap_pairs_follow_the_kinds_rules() -> None:
    from distilkit.pairing.facts import TapFact
    from distilkit.pairing.rules import tap_pairs
    from distilkit.structures import VoxelGrid

    full = VoxelGrid((0.0, -25.6, -2.0), (128, 128, 16), 0.4)
    half, odd = full.coarsen(2), VoxelGrid((0.0, -25.6, -2.0), (100, 100, 12), 0.512)
    s = _facts("student", [TapFact("logits", "voxel_logits", full, channels=20),
                           TapFact("feats", "sparse_features", full, channels=8),
                           TapFact("image", "image_features", camera="cam0", channels=8, shape=(12, 40))])
    t = _facts("teacher", [TapFact("logits", "voxel_logits", half, channels=20),  # logits on another grid: never
                           TapFact("coarse", "sparse_features", half, channels=16),
                           TapFact("odd", "sparse_features", odd, channels=16),  # no integer ratio: never
                           TapFact("image", "image_features", camera="cam1", channels=8, shape=(12, 40))])
    pairs = tap_pairs(s, t)
    assert [(p.student.tap, p.teacher.tap, p.how) for p in pairs] == [("feats", "coarse", "teacher coarser x2")]


def test_an_equal_width_rule_on_a_role_without_a_connector_refuses_other_widths() -> None:
    from distilkit.data.datasets import synthetic_info
    from distilkit.data.params import SyntheticParams
    from distilkit.pairing.facts import TapFact
    from distilkit.pairing.fit import defaults, proposals
    from distilkit.pairing.rules import tap_pairs

    info = synthetic_info(SyntheticParams(**TINY_DATA))
    s = _facts("student", [TapFact("logits", "voxel_logits", info.grid, channels=20),
                           TapFact("vol", "volume_features", info.grid, channels=8)])
    t = _facts("teacher", [TapFact("logits", "voxel_logits", info.grid, channels=20),
                           TapFact("vol", "volume_features", info.grid, channels=16)])
    found = {p.objective: p for p in proposals(tap_pairs(s, t), s, t, info)}
    assert found["monoocc_kl"].connector == "linear"  # the student role: a connector makes the widths equal
    assert found["cleaners"].fits and "teacher_features" not in found["cleaners"].taps  # optional roles unfilled
    assert found["nst"].connector is None and found["nst"].fits  # any widths
    assert not found["pkt"].fits and "sparse_features" in found["pkt"].refused
    assert [p.objective for p in defaults(list(found.values()))] == ["kd", "fitnets"]


@pytest.mark.xdist_group("tiny_runs")  # the worker that trains conftest's tiny runs once
def test_a_trained_teacher_is_read_from_its_run_folder(tmp_path, tmp_path_factory) -> None:
    from _tiny_runs import tiny_runs

    _, results = tiny_runs(tmp_path_factory)
    teacher = results[0].run_dir
    out = tmp_path / "pair.yaml"
    code, _, err = init("--teacher", str(teacher), "--student", "scpnet", "--student-params", *SCPNET, "--yes",
                        "-o", str(out))
    assert code == 0, err
    recipe = yaml.safe_load(out.read_text())
    assert "teacher" not in recipe["stages"]  # trained already: no stage trains it again
    _, stage = distill_stage(recipe)
    ckpt = stage["teacher"]["checkpoint"]
    assert Path(ckpt).is_file() and Path(ckpt).parent.parent == teacher
    assert stage["teacher"]["model"]["adapter"] == "scpnet" and stage["teacher"]["model"]["params"]["channels"] == 4
    assert recipe["data"]["dataset"] == "synthetic-lidar" and recipe["data"]["params"]["scale"] == 8  # its run's


@pytest.mark.slow
@pytest.mark.parametrize("row", sorted(ROWS))
def test_every_written_recipe_trains(row, tmp_path) -> None:
    """Each family pair's written recipe runs end to end at a step a stage (the default suite trains one)."""
    teacher, tp, student, sp, data, _, _ = ROWS[row]
    out = tmp_path / "pair.yaml"
    assert init(*args(teacher, tp, student, sp, data), "--yes", "-o", str(out), "--set", "stages.*.train.steps=1",
                "stages.*.train.batch_size=1")[0] == 0
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["run", str(out), "-q", "--output", str(tmp_path / "runs")]) == 0
    recipe = yaml.safe_load(out.read_text())
    summaries = sorted((tmp_path / "runs").rglob("summary.json"))
    assert len(summaries) == len(recipe["stages"]) and all('"finished"' in p.read_text() for p in summaries)


def test_birds_eye_terms_get_maps_init_makes_of_voxel_taps(tmp_path) -> None:
    """LiCROcc's and the voxel-to-BEV terms read bird's-eye maps no built-in adapter declares: init makes them
    (recipe taps collapsing a voxel tap by max) on the side that needs one, and the recipe validates."""
    out = tmp_path / "pair.yaml"
    code, _, err = init(*args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA), "--yes", "-o", str(out),
                        "--objectives", "licrocc_bev,licrocc_affinity,bev_from_voxels")
    assert code == 0, err
    _, stage = distill_stage(yaml.safe_load(out.read_text()))
    made = {"bev_completion": {"of": "completion", "kind": "bev_features", "collapse": "max"}}
    assert stage["model"]["taps"] == made and stage["teacher"]["taps"] == made
    assert [t["taps"] for t in stage["distill"]] == [{"student": "bev_completion", "teacher": "bev_completion"}] * 2 \
        + [{"student": "bev_completion", "teacher": "completion"}]  # voxel-to-BEV collapses the teacher's itself
    # JS3C-Net's completion lives on a grid twice as coarse: maps compared cell by cell do not fit, resized ones do
    code, text, _ = init(*args("js3cnet", JS3CNET, "scpnet", SCPNET, LIDAR_DATA), "--show")
    text = " ".join(text.replace("│", " ").split())  # the tables' cells, in reading order
    assert code == 0 and "bev_completion bev_completion bev_features teacher coarser x2" in text
    assert "licrocc_bev 4 compares bev_features cell by cell" in text
    assert "licrocc_affinity 40 student: bev_completion, teacher: bev_completion" in text
    assert "bev_from_voxels 2 no student bev_features tap aligns with a teacher sparse_features tap" in text


def test_the_tutorials_init_commands_run_in_miniature(tmp_path, monkeypatch) -> None:
    """The walkthrough's `distilkit init` lines (docs/tutorials/lidar-pair.md), each as written plus small models
    and data, write what the page shows."""
    import re
    import shlex

    page = (ROOT / "docs" / "tutorials" / "lidar-pair.md").read_text()
    lines = [line.strip() for block in re.findall(r"```bash\n(.*?)```", page, re.S) for line in block.splitlines()
             if line.strip().startswith("distilkit init")]
    assert len(lines) == 2  # --show, then --yes -o
    monkeypatch.chdir(tmp_path)
    small = ["--teacher-params", *JS3CNET, "--student-params", *SCPNET, "--data-params", *LIDAR_DATA]
    for line in lines:
        code, _, err = init(*shlex.split(line)[2:], *small)
        assert code == 0, (line, err)
    written = yaml.safe_load((tmp_path / "scpnet_from_js3cnet.yaml").read_text())
    shown = yaml.safe_load(re.search(r"```yaml\n(  student_kd_dskd:.*?)```", page, re.S).group(1))
    assert written["stages"]["student_kd_dskd"]["distill"] == shown["student_kd_dskd"]["distill"]


def _tiny_info():
    from distilkit.data.datasets import synthetic_info
    from distilkit.data.params import SyntheticParams

    return synthetic_info(SyntheticParams(**TINY_DATA))


def _found(s_taps, t_taps, info=None):
    from distilkit.pairing.fit import proposals
    from distilkit.pairing.rules import tap_pairs

    info = info or _tiny_info()
    s, t = _facts("student", s_taps), _facts("teacher", t_taps)
    return {p.objective: p for p in proposals(tap_pairs(s, t), s, t, info)}


def test_maps_masked_by_the_labels_must_be_the_labels_grid_or_coarser() -> None:
    from distilkit.pairing.facts import TapFact
    from distilkit.structures import VoxelGrid

    info = _tiny_info()
    g = info.grid
    finer = VoxelGrid(g.origin, tuple(2 * n for n in g.shape), g.voxel_size / 2)
    for grid, fits in ((g.coarsen(2), True), (g, True), (finer, False)):
        found = _found([TapFact("v", "volume_features", grid, channels=8)],
                       [TapFact("v", "volume_features", grid, channels=8)], info)
        assert found["l2cocc_fsd"].fits == fits and found["monoocc_kl"].fits == fits, grid
        if not fits:
            assert "masks the maps by the labels pooled to their size" in found["monoocc_kl"].refused
        assert found["l2cocc_relation"].fits  # cell by cell too, but masked by nothing


def test_equal_widths_on_a_role_no_connector_projects_are_refused() -> None:
    from distilkit.pairing.facts import TapFact

    g = _tiny_info().grid
    student = [TapFact("logits", "voxel_logits", g, channels=20), TapFact("f", "sparse_features", g, channels=8)]
    found = _found(student, [TapFact("logits", "voxel_logits", g, channels=21),
                             TapFact("f", "sparse_features", g, channels=16)])
    assert found["pvkd"].refused == "needs equal widths on student_logits, where no connector projects (20 and 21 " \
                                    "channels)" or "teacher_logits" in found["pvkd"].refused
    assert not found["pvkd"].fits and found["dskd"].fits  # the sparse pair itself fits any widths
    assert found["kd"].connector == "linear"  # on the student role a connector makes them equal


def test_a_role_only_the_student_fills_prefers_the_cards_taps_and_falls_back_with_a_note() -> None:
    import dataclasses

    from distilkit.pairing.facts import TapFact

    scenes = dataclasses.replace(_tiny_info(), fields=frozenset({"scan", "scan_lengths", "scene", "scene_lengths"}))
    teacher = _facts("teacher", [])
    teacher.capabilities = frozenset({"predict_noise"})
    for taps, want, note in (((TapFact("eps_pred", "points"), TapFact("samples", "points")), "samples", ""),
                             ((TapFact("refined", "points"),), "refined", "prefers samples")):
        s = _facts("student", list(taps))
        s.capabilities = frozenset({"generate"})
        from distilkit.pairing.fit import proposals

        found = {p.objective: p for p in proposals([], s, teacher, scenes)}
        assert found["structural"].taps == {"student": want} and note in found["structural"].note
    s = _facts("student", [TapFact("eps_pred", "points"), TapFact("samples", "points", present=False)])
    s.capabilities = frozenset({"generate"})
    found = {p.objective: p for p in proposals([], s, teacher, scenes)}
    assert not found["vsd"].fits and "declares but does not return" in found["vsd"].refused


def test_a_plug_in_objective_without_a_match_is_paired_by_kind_and_said_so() -> None:
    from pydantic import BaseModel

    from distilkit.cards.base import ObjectiveCard
    from distilkit.pairing.facts import TapFact
    from distilkit.pairing.fit import propose
    from distilkit.pairing.rules import tap_pairs

    class MyCard(ObjectiveCard):
        Params = BaseModel
        CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}

    g = _tiny_info().grid
    s, t = (_facts(r, [TapFact("logits", "voxel_logits", g, channels=20)]) for r in ("student", "teacher"))
    p = propose("mine", MyCard, 1.0, tap_pairs(s, t), s, t, _tiny_info())
    assert p.fits and p.taps == {"student": "logits", "teacher": "logits"} and "declares no match" in p.note


def test_flags_shape_what_is_written(tmp_path) -> None:
    out = tmp_path / "pair.yaml"
    common = args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA)
    assert init(*common, "--yes", "-o", str(out), "--stages", "each", "--no-baseline", "--set", "threads=1")[0] == 0
    recipe = yaml.safe_load(out.read_text())
    assert set(recipe["stages"]) == {"teacher", "student_kd", "student_dskd"} and recipe["threads"] == 1
    code, _, err = init(*common, "--yes", "-o", str(out))
    assert code == 2 and "--force" in err
    assert init(*common, "--yes", "-o", str(out), "--force", "--no-check")[0] == 0
    assert set(yaml.safe_load(out.read_text())["stages"]) == {"teacher", "student", "student_kd_dskd"}
    code, _, err = init(*common, "--yes", "-o", str(out), "--force",
                        "--set", "stages.student_kd_dskd.distill.1.params.per_sample=abc")
    assert code == 2 and "Traceback" not in err and "distill.1.params.per_sample" in err


def test_bad_model_parameters_and_a_failing_forward_are_named(tmp_path, monkeypatch) -> None:
    code, _, err = init("--teacher", "scpnet", "--student", "scpnet", "--teacher-params", "chanels=4", "--yes",
                        "-o", str(tmp_path / "x.yaml"))
    assert code == 2 and "--teacher-params for 'scpnet': chanels" in err and "Traceback" not in err
    import distilkit.pairing.probe

    def fails(*a, **k):
        raise RuntimeError("the user's forward broke")

    monkeypatch.setattr(distilkit.pairing.probe, "probe_taps", fails)
    code, _, err = init(*args("scpnet", SCPNET, "scpnet", SCPNET, LIDAR_DATA), "--show")
    assert code == 2 and "the user's forward broke" in err and "--static" in err


def test_show_lists_every_objective_even_when_no_default_fits() -> None:
    code, out, err = init(*args("lidiff-refine", [], "lidiff", LIDIFF + ["generate_steps=1"], SCENES_DATA), "--show")
    text = " ".join(out.replace("│", " ").split())
    assert code == 0, err
    assert "structural 1 student: samples; needs no teacher" in text and "◆ " not in text.split("chosen)", 1)[1]
