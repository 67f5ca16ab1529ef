"""The teacher run once (issue 58, items 1, 2 and 4): a student trained from the teacher's stored outputs equals the
student trained with the live teacher bit for bit (with and without augmentation), students that share a teacher
read one store built once, a changed tap builds another, an interrupted build resumes, a corrupt shard is named,
and validate refuses what cannot be stored."""

from __future__ import annotations

import copy
import json

import pytest
import torch

from conftest import tiny_recipe
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import DataError, RecipeError
from distilkit.recipe import recipe_from_dict
from distilkit.weights import load_checkpoint


def _two_students(augment: dict | None = None, steps: int = 3, batch_size: int = 1) -> dict:
    """The tiny teacher, and two DSKD students alike but for where the teacher's outputs come from."""
    recipe = tiny_recipe(steps=steps)
    live = recipe["stages"]["student"]
    live["train"]["batch_size"] = batch_size
    if augment is not None:
        live["train"]["augment"] = augment
    stored = copy.deepcopy(live)
    stored["teacher"] = {"from": "teacher", "store": True}
    recipe["stages"]["student_stored"] = stored
    return recipe


def _weights(result) -> dict:
    return load_checkpoint(result.run_dir / "checkpoints" / "last.pt")["student"]


def _losses(result) -> list:
    lines = [json.loads(x) for x in (result.run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in e.items() if k not in ("time", "seconds", "elapsed", "wall")} for e in lines
            if e.get("event") == "train" or "loss" in e]


@pytest.mark.parametrize("augment", [None, {"flip": ["x", "y"], "rotate90": "z"}], ids=["plain", "augmented"])
def test_a_student_from_the_store_equals_the_student_with_the_live_teacher_bit_for_bit(tmp_path, augment) -> None:
    results = {r.name: r for r in Pipeline(recipe_from_dict(_two_students(augment)), tmp_path / "runs",
                                           quiet=True).run()}
    live, stored = _weights(results["student"]), _weights(results["student_stored"])
    assert set(live) == set(stored) and all(torch.equal(live[k], stored[k]) for k in live)
    assert _losses(results["student"]) == _losses(results["student_stored"])
    for r in results.values():  # the loop's time waiting for the loader's batches (the store read with them)
        assert 0 < r.summary["input_wait_seconds"] < r.summary["train_seconds"]
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    manifest = json.loads((store / "manifest.json").read_text())
    assert manifest["draws"] == (8 if augment else 1) and manifest["taps"] and manifest["bytes"] > 0
    assert len(manifest["samples"]) == 2 and all(s["sha256"] for s in manifest["shards"])


def test_the_build_measures_whether_the_stored_rows_are_the_live_teachers_batched_output(tmp_path) -> None:
    """The stored rows are each sample's output alone; the build compares the teacher's forward on the first batch
    with them and records the largest difference, measured here again independently: where it is 0 the students
    are the same bits, else they differ by that much at their first step (oneDNN may compute a batch of two
    differently from one sample; Adam's normalised steps then carry any last-bit difference on)."""
    from distilkit.engine.assemble.runs import load_run

    pipe = Pipeline(recipe_from_dict(_two_students(batch_size=2)), tmp_path / "runs", quiet=True)
    results = {r.name: r for r in pipe.run()}
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    check = json.loads((store / "manifest.json").read_text())["batch_check"]
    stage = pipe.resolved.stages["student_stored"]
    teacher = load_run(pipe.weights("teacher"), model=stage.teacher, info=pipe.resolved.data_info, role="teacher")
    split = pipe.dataset("train")
    with torch.no_grad():
        together = teacher(pipe.collate([split[0], split[1]]))["completion"]
        alone = [teacher(pipe.collate([split[i]]))["completion"] for i in (0, 1)]
    expected = max((together.feats[together.coords[:, 0] == b] - a.feats).abs().max().item()
                   for b, a in enumerate(alone))
    assert check["batch"] == 2 and check["max_difference"] == expected
    live, stored = _losses(results["student"])[0], _losses(results["student_stored"])[0]
    if expected == 0:
        assert _losses(results["student"]) == _losses(results["student_stored"])
    else:
        assert live["ce"] == stored["ce"] and live["kd_dskd"] == pytest.approx(stored["kd_dskd"], rel=1e-5)


def test_a_batch_reads_each_samples_rows_under_its_own_draw(tmp_path) -> None:
    """Two samples under draws 3 and 5: the batch's sparse rows are each sample's rows under its draw, computed
    alone, with its batch index — in batch order."""
    from distilkit.data.augment import Augmentation
    from distilkit.engine.assemble.runs import load_run
    from distilkit.engine.store.teacher_outputs import TeacherOutputs

    recipe = _two_students({"flip": ["x", "y"], "rotate90": "z"}, steps=1)
    recipe["stages"].pop("student")
    pipe = Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True)
    pipe.run()
    (folder,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    store = TeacherOutputs(folder)
    stage = pipe.resolved.stages["student_stored"]
    teacher = load_run(pipe.weights("teacher"), model=stage.teacher, info=pipe.resolved.data_info, role="teacher")
    aug = Augmentation(stage.spec.train.augment, pipe.resolved.data_info.grid)
    split = pipe.dataset("train")
    ids = [split.sample_id(1), split.sample_id(0)]
    got = store.batch(ids, [3, 5], torch.device("cpu"))["completion"]
    for b, (i, d) in enumerate(((1, 3), (0, 5))):
        with torch.no_grad():
            want = teacher(pipe.collate([aug.apply(split[i], d)]))["completion"]
        rows = got.coords[:, 0] == b
        assert torch.equal(got.coords[rows, 1:], want.coords[:, 1:]) and torch.equal(got.feats[rows], want.feats)
    assert bool((got.coords[:, 0].diff() >= 0).all())


def test_students_sharing_a_teacher_read_one_store_built_once_and_a_changed_tap_builds_another(
        tmp_path, monkeypatch) -> None:
    import distilkit.engine.train.teacher_store as ts

    built = []  # (stage, shard) computed: the teacher runs over each store's samples once
    real = ts._Build._shard
    monkeypatch.setattr(ts._Build, "_shard", lambda self, s: built.append((self.run.name, s)) or real(self, s))
    recipe = _two_students()
    recipe["stages"]["student"]["teacher"] = {"from": "teacher", "store": True}
    recipe["stages"]["student_stored"]["distill"] = [{"name": "dskd", "weight": 3.0}]  # another student, same taps
    recipe["stages"]["student_logits"] = copy.deepcopy(recipe["stages"]["student"])
    recipe["stages"]["student_logits"]["distill"] = [{"name": "kd"}]  # reads the teacher's logits instead
    Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert len(built) == 2 and len({b[0] for b in built}) == 2  # one store for the two DSKD students, one for
    # the logits, each one shard of the two samples
    assert len(list((tmp_path / "runs" / "tiny").glob("teacher-store-*"))) == 2


def test_an_interrupted_build_resumes_at_its_first_unfinished_shard(tmp_path, monkeypatch) -> None:
    import distilkit.engine.train.teacher_store as ts

    recipe = _two_students()
    recipe["stages"]["student_stored"]["teacher"]["store"] = {"shard": 1}  # two shards for the two samples
    recipe["stages"].pop("student")
    real, written = ts.write_shard, []

    def once(folder, index, tensors, extra):
        if written:
            raise KeyboardInterrupt  # killed while the second shard is computed
        written.append(index)
        return real(folder, index, tensors, extra)

    monkeypatch.setattr(ts, "write_shard", once)
    with pytest.raises(KeyboardInterrupt):
        Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    first = (store / "shard-00000.safetensors").stat().st_mtime_ns
    assert not (store / "manifest.json").exists()
    monkeypatch.setattr(ts, "write_shard", lambda *a: written.append(a[1]) or real(*a))
    Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    assert written == [0, 1] and (store / "shard-00000.safetensors").stat().st_mtime_ns == first
    manifest = json.loads((store / "manifest.json").read_text())
    assert [s["count"] for s in manifest["shards"]] == [1, 1]
    monkeypatch.setattr(ts, "write_shard", real)  # a build never interrupted writes the same shards
    Pipeline(recipe_from_dict(recipe), tmp_path / "fresh", quiet=True).run()
    (fresh,) = (tmp_path / "fresh" / "tiny").glob("teacher-store-*")
    assert fresh.name == store.name
    assert [s["sha256"] for s in json.loads((fresh / "manifest.json").read_text())["shards"]] == \
        [s["sha256"] for s in manifest["shards"]]


def test_a_corrupt_shard_is_named(tmp_path) -> None:
    from distilkit.engine.store.teacher_outputs import TeacherOutputs

    recipe = _two_students(steps=1)
    recipe["stages"].pop("student")
    Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    shard = store / "shard-00000.safetensors"
    data = bytearray(shard.read_bytes())
    data[-1] ^= 0xFF
    shard.write_bytes(bytes(data))
    reader = TeacherOutputs(store)
    with pytest.raises(DataError, match=r"shard-00000\.safetensors: the teacher store's shard is missing, truncated or "
                                        r"altered .*delete it and run the stage again"):
        reader.batch([reader.manifest["samples"][0]], [0], torch.device("cpu"))
    shard.unlink()  # as the message says: the next run rebuilds that shard and reads the store
    from distilkit.engine.store.teacher_outputs import whole

    assert not whole(store)
    Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run(rerun=["student_stored"])
    assert whole(store) and TeacherOutputs(store).batch([reader.manifest["samples"][0]], [0], torch.device("cpu"))


@pytest.mark.parametrize("change, words", [
    ({"teacher": {"ema": True, "store": True}}, "moving average changes at every step"),
    ({"teacher": {"from": "teacher", "mode": "train", "store": True}}, "mode: train"),
    ({"teacher": {"from": "teacher", "store": True}, "distill": [{"name": "dskd"}],
      "train": {"steps": 1, "augment": {"rotate": "z"}}}, "continuous transforms"),
])
def test_validate_refuses_what_cannot_be_stored_with_one_line_naming_why(change, words) -> None:
    from distilkit.engine.assemble.resolve import resolve

    recipe = tiny_recipe(steps=1)
    recipe["stages"]["student"].update(change)
    with pytest.raises(RecipeError, match=r"stages\.student\.teacher\.store: .*" + words):
        resolve(recipe_from_dict(recipe))


def test_validate_refuses_a_store_for_a_term_that_calls_the_teacher(capsys) -> None:
    from distilkit.cli import main

    assert main(["validate", "--static", "recipes/scorelidar.yaml", "--set", "stages.student.teacher.store=true"]) == 2
    assert "calls the teacher's predict_noise(): it needs the teacher itself" in capsys.readouterr().err


@pytest.mark.slow
def test_the_quickstart_students_from_a_store_equal_the_live_ones(tmp_path) -> None:
    """The quickstart as shipped (4-frame teacher, 1-frame students, batches of 2, 60 steps): its DIST and DSKD
    students trained from the teacher's stores equal the live ones bit for bit, and every test score is the same."""
    from distilkit.recipe import load_recipe

    recipe = load_recipe("recipes/quickstart.yaml").model_dump(mode="json", by_alias=True, exclude_none=True)
    for name in ("student_dist", "student_dskd"):
        stored = copy.deepcopy(recipe["stages"][name])
        stored["teacher"] = {"from": "teacher", "store": True}
        stored.pop("label", None)
        recipe["stages"][f"{name}_stored"] = stored
    results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()}
    for name in ("student_dist", "student_dskd"):
        live, stored = _weights(results[name]), _weights(results[f"{name}_stored"])
        assert all(torch.equal(live[k], stored[k]) for k in live), name
        scores = [{which: {k: v for k, v in results[n].summary["test"][which].items() if k != "seconds_per_sample"}
                   for which in ("best", "last")} for n in (name, f"{name}_stored")]
        assert scores[0] == scores[1], name  # every score the same (the forward's timing aside)
    # DIST reads the teacher's logits, DSKD its sparse features: one store for each set of taps
    assert len(list((tmp_path / "runs" / "quickstart").glob("teacher-store-*"))) == 2


@pytest.mark.slow
def test_a_paper_size_js3cnet_student_from_the_store_equals_the_live_one(tmp_path) -> None:
    """recipes/paper/js3cnet.yaml at the paper's sizes (JS3C-Net at ``size: paper`` on the full 256 x 256 x 32 grid of
    the synthetic streets, a 5-scan teacher, a 1-scan DSKD student on the sparse completion features, the paper's
    flips and quarter turns): two steps of the student from the teacher's store (each sample under the 8 draws of
    the group) equal two steps with the live teacher bit for bit, weights, losses and test scores."""
    from distilkit.bench.fixtures import paper_recipe

    recipe = paper_recipe("js3cnet", quick=False, test=False, num_train=1)
    del recipe["stages"]["student"]
    for name, steps in (("teacher", 1), ("student_dskd", 2)):
        train = recipe["stages"][name]["train"]
        train.pop("epochs")
        train.update(steps=steps, batch_size=1)
    stored = copy.deepcopy(recipe["stages"]["student_dskd"])
    stored["teacher"] = {"from": "teacher", "store": True}
    stored.pop("label", None)
    recipe["stages"]["student_dskd_stored"] = stored
    results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()}
    live, from_store = _weights(results["student_dskd"]), _weights(results["student_dskd_stored"])
    assert set(live) == set(from_store) and all(torch.equal(live[k], from_store[k]) for k in live)
    assert _losses(results["student_dskd"]) == _losses(results["student_dskd_stored"])
    scores = [{which: {k: v for k, v in results[n].summary["test"][which].items() if k != "seconds_per_sample"}
               for which in ("best", "last")} for n in ("student_dskd", "student_dskd_stored")]
    assert scores[0] == scores[1]
    (store,) = (tmp_path / "runs" / "js3cnet_paper").glob("teacher-store-*")
    manifest = json.loads((store / "manifest.json").read_text())
    assert manifest["draws"] == 8 and len(manifest["samples"]) == 1
