"""Trainer and pipeline: frozen teacher, caching by content, resume, checkpoints, NaN handling."""

from __future__ import annotations

import json

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import make_trainer, tiny_recipe
from distilkit.weights import load_checkpoint
from distilkit.engine.train.pipeline import Pipeline
from distilkit.engine.assemble.runs import load_run
from distilkit.engine.train.trainer import Trainer
from distilkit.errors import DataError, NonFiniteLossError, RecipeError, TapError
from distilkit.engine.assemble.resolve import resolve
from distilkit.recipe import recipe_from_dict


def pipeline(tmp_path, recipe: dict) -> Pipeline:
    return Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)


def poison_terms(monkeypatch, change) -> None:
    """Let ``change(trainer, terms, call)`` alter the loss terms of the ``call``-th evaluation (from 1)."""
    calls = {"n": 0}
    orig = Trainer.loss_terms

    def poisoned(self, batch):
        terms = orig(self, batch)
        calls["n"] += 1
        change(self, terms, calls["n"])
        return terms

    monkeypatch.setattr(Trainer, "loss_terms", poisoned)


@pytest.mark.plots
def test_run_then_reuse_every_stage(tmp_path) -> None:
    pipe = pipeline(tmp_path, tiny_recipe())
    first = pipe.run()
    assert [r.reused for r in first] == [False, False]
    for r in first:
        d = r.run_dir
        assert (d / "summary.json").is_file() and (d / "recipe.resolved.yaml").is_file()
        assert (d / "checkpoints" / "last.pt").is_file() and (d / "checkpoints" / "best.pt").is_file()
        lines = [json.loads(x) for x in (d / "metrics.jsonl").read_text().splitlines()]
        assert any("eval" in x for x in lines) and any("loss" in x for x in lines)
        assert 0.0 <= r.summary["best"]["scores"]["miou"] <= 1.0
    assert (pipe.root / "report.md").is_file() and (pipe.root / "report.png").stat().st_size > 1000
    student = first[1]
    assert "kd_dskd" in json.loads((student.run_dir / "metrics.jsonl").read_text().splitlines()[0])
    # checkpoints hold the student only (no teacher weights)
    ckpt = load_checkpoint(student.run_dir / "checkpoints" / "last.pt")
    assert set(ckpt) >= {"student", "optimizer", "rng", "step"} and "teacher" not in ckpt
    mtimes = [(r.run_dir / "summary.json").stat().st_mtime_ns for r in first]
    relabelled = tiny_recipe()
    relabelled["stages"]["student"]["label"] = "student, renamed"  # cosmetic: reused, shown with the new label
    again = pipeline(tmp_path, relabelled).run()
    assert [r.reused for r in again] == [True, True]
    assert [(r.run_dir / "summary.json").stat().st_mtime_ns for r in again] == mtimes
    assert again[1].summary["label"] == "student, renamed"


def test_changing_the_teacher_changes_the_student_identity(tmp_path) -> None:
    a = pipeline(tmp_path, tiny_recipe())
    r = tiny_recipe()
    r["stages"]["teacher"]["optimizer"] = {"lr": 0.01}
    b = pipeline(tmp_path, r)
    assert a.hashes["teacher"] != b.hashes["teacher"] and a.hashes["student"] != b.hashes["student"]
    r2 = tiny_recipe()
    r2["stages"]["teacher"]["train"]["log_every"] = 5  # logging does not change what is trained
    assert pipeline(tmp_path, r2).hashes == a.hashes


@pytest.fixture(scope="module")
def one_step_runs(tmp_path_factory) -> "Path":
    """The folder of a finished tiny teacher-and-student run of one step each (``tiny_recipe(steps=1)``), trained
    once a process for the tests that read it (tests/_tiny_runs.py; it asserts that both stages were trained, not
    reused; a test that changes it works on a copy)."""
    from _tiny_runs import tiny_runs

    return tiny_runs(tmp_path_factory)[0]


def copy_of(runs, tmp_path):
    import shutil

    shutil.copytree(runs / "runs", tmp_path / "runs")
    return tmp_path


@pytest.mark.xdist_group("tiny_runs")  # tests/_tiny_runs.py
def test_teacher_is_frozen_and_unchanged_by_a_step(one_step_runs, device) -> None:
    """Three training steps of a distilled student on the device of --device: the student moves, the teacher not."""
    pipe = pipeline(one_step_runs, tiny_recipe(steps=1))  # the shared finished run: its teacher is read only
    stage = pipe.resolved.stages["student"]
    teacher = load_run(pipe.run_dir("teacher"), model=stage.teacher, info=pipe.resolved.data_info,
                       role="teacher").to(device)
    before = {k: v.clone() for k, v in teacher.state_dict().items()}
    assert not teacher.training and not any(p.requires_grad for p in teacher.parameters())
    trainer = make_trainer(pipe, "student", teacher, device=device)
    start = {k: v.clone() for k, v in trainer.student.state_dict().items()}
    for step in range(3):
        logged = trainer.train_step(trainer.prepare(trainer.plan.batch(trainer.train_set, trainer.collate, step)), step)
        assert all(v == v for v in logged.values() if isinstance(v, float))  # finite numbers logged, no NaN
    assert all(p.device.type == device.type for p in trainer.student.parameters())
    assert any(not torch.equal(start[k], v) for k, v in trainer.student.state_dict().items())
    after = teacher.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)  # weights and BN buffers
    assert not teacher.training


def test_resume_after_interruption(tmp_path, device) -> None:
    """On the device of --device: what a checkpoint holds (weights, optimizer, the RNG states) resumes there."""
    recipe = tiny_recipe(steps=4, distill=False, device=device)
    recipe["stages"]["teacher"]["train"]["eval_every"] = 4
    pipeline(tmp_path, recipe).run(stop_after=2)
    pipe = pipeline(tmp_path, recipe)
    run_dir = pipe.run_dir("teacher")
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"] == 2
    assert not (run_dir / "summary.json").exists()
    results = pipe.run()
    assert results[0].summary["steps"] == 4 and not results[0].reused
    events = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert {"event": "resume", "step": 2} in events
    # the resumed run equals an uninterrupted one
    fresh = pipeline(tmp_path / "other", recipe).run()
    a = load_checkpoint(run_dir / "checkpoints" / "last.pt")["student"]
    b = load_checkpoint(fresh[0].run_dir / "checkpoints" / "last.pt")["student"]
    assert all(torch.allclose(a[k].float(), b[k].float(), atol=1e-5) for k in a)


def test_nan_loss_stops_with_a_clear_error_and_keeps_the_checkpoint(tmp_path, monkeypatch) -> None:
    pipe = pipeline(tmp_path, tiny_recipe(steps=3, distill=False))

    def nan_ce(self, terms, call):
        if call == 2:
            terms["ce"] = terms["ce"] * float("nan")

    poison_terms(monkeypatch, nan_ce)
    with pytest.raises(NonFiniteLossError, match=r"ce.*the last checkpoint \(.*last\.pt, step 1\) is kept"):
        pipe.run()
    assert load_checkpoint(pipe.run_dir("teacher") / "checkpoints" / "last.pt")["step"] == 1


def test_a_run_that_fails_before_any_checkpoint_says_none_was_kept(tmp_path, monkeypatch) -> None:
    recipe = tiny_recipe(steps=3, distill=False)
    recipe["stages"]["teacher"]["train"]["checkpoint_every"] = 10
    pipe = pipeline(tmp_path, recipe)

    def nan_ce(self, terms, call):
        if call == 2:
            terms["ce"] = terms["ce"] * float("nan")

    poison_terms(monkeypatch, nan_ce)
    with pytest.raises(NonFiniteLossError, match=r"no checkpoint had been written yet") as err:
        pipe.run()
    assert "is kept" not in str(err.value)
    assert not (pipe.run_dir("teacher") / "checkpoints" / "last.pt").exists()


def test_corrupt_checkpoint_is_a_clear_error(tmp_path) -> None:
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="not a readable checkpoint"):
        load_checkpoint(bad)


def test_js3cnet_dskd_recipe_runs(tmp_path) -> None:
    results = pipeline(tmp_path, tiny_recipe(steps=1, adapter="js3cnet")).run()
    assert [r.summary["status"] for r in results] == ["finished", "finished"]


def test_a_changed_component_version_retrains_exactly_its_stages(tmp_path, monkeypatch) -> None:
    from distilkit.registry import OBJECTIVES, TASK_LOSSES

    DSKD, VoxelLovasz = OBJECTIVES.card("dskd"), TASK_LOSSES.card("lovasz")  # a component's version is its card's
    base = pipeline(tmp_path, tiny_recipe()).hashes
    monkeypatch.setattr(DSKD, "VERSION", DSKD.VERSION + 1)  # only the student uses DSKD
    bumped = pipeline(tmp_path, tiny_recipe()).hashes
    assert bumped["teacher"] == base["teacher"] and bumped["student"] != base["student"]
    monkeypatch.setattr(VoxelLovasz, "VERSION", VoxelLovasz.VERSION + 1)  # both stages train with Lovász
    both = pipeline(tmp_path, tiny_recipe()).hashes
    assert both["teacher"] != base["teacher"] and both["student"] != bumped["student"]


def test_generator_and_distilkit_versions_are_part_of_the_identity(tmp_path, monkeypatch) -> None:
    import distilkit.engine.store.identity as pl
    from distilkit.registry import DATASETS

    base = pipeline(tmp_path, tiny_recipe()).hashes
    entry = DATASETS.entry("synthetic-lidar")
    monkeypatch.setitem(entry.meta, "version", entry.meta["version"] + 1)
    assert all(pipeline(tmp_path, tiny_recipe()).hashes[k] != base[k] for k in base)
    monkeypatch.setitem(entry.meta, "version", entry.meta["version"] - 1)
    monkeypatch.setattr(pl, "__version__", "99.0")
    assert all(pipeline(tmp_path, tiny_recipe()).hashes[k] != base[k] for k in base)


@pytest.mark.xdist_group("tiny_runs")  # tests/_tiny_runs.py
def test_rerun_retrains_the_stage_and_its_students_and_keeps_the_old_run(one_step_runs, tmp_path) -> None:
    """On a copy of the shared finished run: ``--rerun teacher`` retrains both stages and keeps the old folders."""
    tmp_path = copy_of(one_step_runs, tmp_path)
    pipe = pipeline(tmp_path, tiny_recipe(steps=1))
    results = pipe.run(rerun=["teacher"])
    assert [r.reused for r in results] == [False, False]  # the student depends on the teacher
    kept = sorted(p.name for p in pipe.root.iterdir() if ".replaced-" in p.name)
    assert len(kept) == 2 and all((pipe.root / k / "summary.json").is_file() for k in kept)
    again = pipeline(tmp_path, tiny_recipe(steps=1)).run(rerun=["student"])
    assert [r.reused for r in again] == [True, False]
    from distilkit.errors import RecipeError

    with pytest.raises(RecipeError, match="did you mean 'student'"):
        pipeline(tmp_path, tiny_recipe(steps=1)).run(rerun=["studnet"])


def test_a_nan_gradient_with_a_finite_loss_stops_before_the_weights_change(tmp_path, monkeypatch) -> None:
    pipe = pipeline(tmp_path, tiny_recipe(steps=3, distill=False))

    def sqrt_at_zero(self, terms, call):
        if call >= 2:  # sqrt(0) = 0 is finite, its gradient is not (the blame pass recomputes it)
            w = next(self.student.parameters())
            terms["lovasz"] = terms["lovasz"] + torch.sqrt((w - w.detach()).abs().sum())

    poison_terms(monkeypatch, sqrt_at_zero)
    with pytest.raises(NonFiniteLossError, match=r"stage 'teacher', step 2: the gradient .*lovasz"):
        pipe.run()
    ckpt = load_checkpoint(pipe.run_dir("teacher") / "checkpoints" / "last.pt")
    assert ckpt["step"] == 1
    assert all(torch.isfinite(v).all() for v in ckpt["student"].values() if v.is_floating_point())


def test_resume_leaves_no_duplicate_log_lines(tmp_path) -> None:
    recipe = tiny_recipe(steps=4, distill=False)
    recipe["stages"]["teacher"]["train"].update(eval_every=4, checkpoint_every=2)
    pipeline(tmp_path, recipe).run(stop_after=3)  # log lines for steps 1-3, checkpoint at step 2
    pipe = pipeline(tmp_path, recipe)
    pipe.run()
    steps = [json.loads(x).get("step") for x in (pipe.run_dir("teacher") / "metrics.jsonl").read_text().splitlines()
             if "loss" in json.loads(x)]
    assert steps == [1, 2, 3, 4]


def test_scores_are_reported_on_the_test_split_at_best_and_last(tmp_path) -> None:
    results = pipeline(tmp_path, tiny_recipe(steps=2, distill=False)).run()
    s = results[0].summary
    assert s["report_split"] == "test"
    assert {"best", "last", "best_step", "last_step"} <= set(s["test"])
    assert s["test"]["best_step"] == s["best"]["step"]
    report = (results[0].run_dir.parent / "report.md").read_text()
    assert "test split" in report and "best validation mIoU" in report


def test_cuda_rng_state_round_trips_through_a_checkpoint(tmp_path, monkeypatch) -> None:
    """No GPU here: the CUDA generator functions are replaced by fakes holding two devices' states. A process that
    has not used CUDA (a CPU run on a machine with a GPU) saves none: asking would start a CUDA context, and fails in
    a forked child of a process that used CUDA (seen on an H200)."""
    from distilkit.engine.train.randomness import rng_state, set_rng_state
    from distilkit.files import atomic_torch_save

    states = [torch.arange(8, dtype=torch.uint8), torch.arange(8, 16, dtype=torch.uint8)]
    restored: list[list[torch.Tensor]] = []
    asked: list[int] = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: asked.append(1) or [s.clone() for s in states])
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", lambda s: restored.append(list(s)))
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)
    assert rng_state()["cuda"] == [] and not asked  # CUDA not used by this process: not asked
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    atomic_torch_save(tmp_path / "c.pt", {"student": {}, "rng": rng_state()})
    loaded = load_checkpoint(tmp_path / "c.pt")  # weights_only loading keeps the CUDA states
    set_rng_state(loaded["rng"])
    assert len(restored) == 1 and all(torch.equal(a, b) for a, b in zip(restored[0], states))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)  # resumed on a machine with fewer GPUs: left alone
    set_rng_state(loaded["rng"])
    assert len(restored) == 1


def test_init_from_a_stage_starts_from_its_weights(tmp_path) -> None:
    r = tiny_recipe(steps=2, distill=False)
    r["stages"]["finetune"] = {**r["stages"]["teacher"], "init": {"from": "teacher"},
                               "train": {**r["stages"]["teacher"]["train"], "steps": 1}}
    pipe = pipeline(tmp_path, r)
    assert pipe.resolved.order == ["teacher", "finetune"]
    teacher, finetune = pipe.run()
    log = [json.loads(x) for x in (finetune.run_dir / "metrics.jsonl").read_text().splitlines()]
    assert log[0]["event"] == "init" and log[0]["left_out"] == [] and "teacher-" in log[0]["from"]
    # the fine-tuned weights differ from the teacher's by one optimizer step, not by a fresh initialisation
    a = load_checkpoint(teacher.run_dir / "checkpoints" / "best.pt")["student"]
    b = load_checkpoint(finetune.run_dir / "checkpoints" / "last.pt")["student"]
    fresh = Pipeline(recipe_from_dict(tiny_recipe(distill=False)), tmp_path / "other", quiet=True)
    w = next(k for k, v in a.items() if v.dtype.is_floating_point and v.numel() > 8)
    step = (a[w] - b[w]).abs().max()
    assert 0 < step < 0.05 and step < (a[w] - torch.zeros_like(a[w])).abs().max()
    # retraining the teacher retrains the stage that starts from it
    assert pipe.rerun_set(["teacher"]) == {"teacher", "finetune"}
    assert fresh.hashes["teacher"] == pipe.hashes["teacher"] and "finetune" not in fresh.hashes


def test_init_from_another_adapter_needs_strict_false_and_a_file_must_fit(tmp_path) -> None:
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["other"] = {"model": {"adapter": "js3cnet", "params": {"seg_channels": 4, "embed": 4, "ssc_channels": 4,
                                                                        "pvi_hidden": 4, "knn": 4}},
                            "init": {"from": "teacher"}, "train": r["stages"]["teacher"]["train"]}
    with pytest.raises(RecipeError, match="stages.other.init.from.*strict: false"):
        pipeline(tmp_path, r)
    r["stages"]["other"]["init"]["strict"] = False
    pipeline(tmp_path, r)  # allowed: loads what fits by name and shape
    bad = tmp_path / "w.pt"
    torch.save({"state_dict": {"not.a.weight": torch.zeros(3)}}, bad)
    r2 = tiny_recipe(steps=1, distill=False)
    r2["stages"]["teacher"]["init"] = {"checkpoint": str(bad)}
    with pytest.raises(DataError, match="weights do not fit.*1 unexpected: not.a.weight"):
        pipeline(tmp_path, r2).run()


def test_recipe_taps_record_submodules_and_feed_objectives(tmp_path) -> None:
    r = tiny_recipe(steps=1)
    mid = {"module": "net.completion.upper", "kind": "feature_map"}
    r["stages"]["teacher"]["model"]["taps"] = {"upper": mid}
    r["stages"]["student"]["model"]["taps"] = {"upper": mid}
    r["stages"]["student"]["distill"] = [{"name": "fitnets", "taps": {"student": "upper", "teacher": "upper"}}]
    pipe = pipeline(tmp_path, r)
    plain = pipeline(tmp_path / "b", tiny_recipe(steps=1))
    assert pipe.hashes["teacher"] != plain.hashes["teacher"]  # recorded taps are part of the identity
    _, student = pipe.run()
    assert "kd_fitnets" in (student.run_dir / "metrics.jsonl").read_text()
    # the recorded value is the submodule's output, every forward pass
    from distilkit.engine.assemble.runs import build_model
    from distilkit.data.lidar import collate_lidar

    model = build_model(pipe.resolved.stages["student"].student, pipe.resolved.data_info).eval()
    seen = []
    model.net.completion.upper.register_forward_hook(lambda m, a, out: seen.append(out))
    with torch.no_grad():
        out = model(collate_lidar([pipe.dataset("train")[0]]))
    assert torch.equal(out["upper"], seen[0]) and out["upper"].dim() == 5


def test_recorders_of_every_registered_kind_and_a_plugins(tmp_path) -> None:
    """output, input and method (MMRazor's kinds) record what they say; a plugin's recorder plugs in by name."""
    from distilkit.data.lidar import collate_lidar
    from distilkit.engine.assemble.recorders import attach_recorders
    from distilkit.engine.assemble.runs import build_model
    from distilkit.recipe import HookTapSpec
    from distilkit.registry import RECORDERS

    pipe = pipeline(tmp_path, tiny_recipe(steps=1, distill=False))
    stage = pipe.resolved.stages["teacher"]
    torch.manual_seed(0)
    model = build_model(stage.student, pipe.resolved.data_info).eval()
    seen: dict[str, list] = {"in": [], "out": []}
    model.net.completion.upper.register_forward_hook(lambda m, a, out: seen["in"].append(a[0]) or
                                                     seen["out"].append(out))  # returns None: output unchanged
    RECORDERS.add("doubled", lambda sub, spec, record: sub.register_forward_hook(lambda m, a, out: record(2 * out)),
                  description="test")  # record() returns None: the hook leaves the output as it is
    try:
        attach_recorders(model, {name: HookTapSpec(module="net.completion.upper", kind="feature_map", **kw)
                                 for name, kw in (("o", {}), ("i", {"at": "input"}),
                                                  ("m", {"at": "method", "method": "forward"}),
                                                  ("d", {"at": "doubled"}))})
        with torch.no_grad():
            out = model(collate_lidar([pipe.dataset("train")[0]]))
    finally:
        RECORDERS.remove("doubled")
    assert torch.equal(out["o"], seen["out"][0]) and torch.equal(out["i"], seen["in"][0])
    assert torch.equal(out["m"], seen["out"][0]) and torch.equal(out["d"], 2 * seen["out"][0])
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["teacher"]["model"]["taps"] = {"x": {"module": "net", "kind": "feature_map", "at": "outptu"},
                                               "y": {"module": "net", "kind": "feature_map", "at": "method"}}
    with pytest.raises(RecipeError) as err:
        pipeline(tmp_path / "bad", r)
    assert "stages.teacher.model.taps.x.at: unknown recorder 'outptu'; did you mean 'output'" in str(err.value)
    assert "stages.teacher.model.taps.y.method: `at: method` needs the method's name" in str(err.value)


def test_recipe_taps_name_a_wrong_module_or_kind(tmp_path) -> None:
    r = tiny_recipe(steps=1, distill=False)
    r["stages"]["teacher"]["model"]["taps"] = {"x": {"module": "net.completion.uper", "kind": "feature_map"}}
    with pytest.raises(TapError, match="no submodule 'net.completion.uper'; did you mean 'net.completion.upper'"):
        pipeline(tmp_path, r).run()
    r["stages"]["teacher"]["model"]["taps"] = {"x": {"module": "net.completion.upper", "kind": "scalar"}}
    with pytest.raises(TapError, match="teacher.*tap 'x': expected a 0-d tensor"):
        pipeline(tmp_path / "2", r).run()
    r["stages"]["teacher"]["model"]["taps"] = {"logits": {"module": "net", "kind": "vector"}}
    with pytest.raises(RecipeError, match="(?s)already has a tap 'logits'.*unknown tap kind 'vector'"):
        pipeline(tmp_path / "3", r)


def test_a_stage_lists_its_upstream_edges_in_one_place_and_order_needs_and_downstream_read_them() -> None:
    from distilkit.engine.train.pipeline import downstream
    from distilkit.recipe import needed_stages, stage_order

    r = tiny_recipe(steps=1)
    r["stages"]["finetune"] = {**r["stages"]["teacher"], "init": {"from": "student", "strict": False}}
    recipe = recipe_from_dict(r)
    assert recipe.stages["student"].edges() == {"teacher": "teacher"}
    assert recipe.stages["finetune"].edges() == {"init": "student"} and recipe.stages["teacher"].edges() == {}
    assert stage_order(recipe) == ["teacher", "student", "finetune"]
    assert needed_stages(recipe, {"finetune"}) == {"teacher", "student", "finetune"}
    res = resolve(recipe, "edges")
    assert downstream(res, {"teacher"}) == {"teacher", "student", "finetune"}
    assert downstream(res, {"student"}) == {"student", "finetune"}
    r["stages"]["teacher"]["init"] = {"from": "finetune"}  # a cycle through an init edge
    with pytest.raises(RecipeError, match="cycle of teacher/init stages"):
        stage_order(recipe_from_dict(r))


def test_a_moved_data_folder_keeps_its_stages_and_a_changed_file_does_not(tmp_path) -> None:
    """Identity fingerprints a SemanticKITTI folder by its files (names, sizes, modification times), not its path."""
    import os
    import shutil

    from conftest import FIXTURES

    first = tmp_path / "a" / "kitti"
    shutil.copytree(FIXTURES / "semantickitti-sample", first, copy_function=shutil.copy2)

    def hashes(root) -> dict[str, str]:
        r = tiny_recipe(steps=1)
        r["data"] = {"dataset": "semantickitti", "params": {"root": str(root), "scale": 8, "input_frames": 2,
                                                            "train_sequences": ["00"], "val_sequences": ["00"]}}
        return pipeline(tmp_path, r).hashes

    before = hashes(first)
    moved = tmp_path / "b" / "elsewhere"
    moved.parent.mkdir()
    os.rename(first, moved)
    assert hashes(moved) == before
    scan = moved / "sequences" / "00" / "velodyne" / "000000.bin"
    scan.write_bytes(scan.read_bytes()[:-16])  # one point fewer
    assert all(hashes(moved)[k] != before[k] for k in before)
