"""The teacher store's lossy layouts and shared builds (issue 58, items 2 and 4): each layout read back against an
independent float64 computation of what it keeps; validate refusing a layout that drops what a term reads; processes
that build one store claim disjoint shards, and a build that would wait with --no-wait names the shard."""

from __future__ import annotations

import copy
import fcntl
import json
import math
import os

import pytest
import torch

from conftest import tiny_recipe
from distilkit.engine.store.teacher_outputs import (FORMAT, MANIFEST, TeacherOutputs, sample_tensors, tap_layout,
                                                   write_shard)
from distilkit.engine.train.pipeline import Pipeline
from distilkit.errors import RecipeError, RunLockedError
from distilkit.recipe import recipe_from_dict

C, SHAPE = 8, (6, 5, 4)


def _outputs(seed: int) -> tuple[dict, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    logits = torch.randn(1, C, *SHAPE, generator=g) * 3
    feats = torch.randn(1, 3, *SHAPE, generator=g)
    labels = torch.randint(0, 3, SHAPE, generator=g)
    labels[0, 0, :] = 255  # a few ignored voxels
    return {"logits": logits, "feats": feats}, labels


def _folder(tmp_path, name: str):
    (tmp_path / name).mkdir()
    return tmp_path / name


def _store(folder, layout: dict) -> tuple[TeacherOutputs, list]:
    """Two samples written in ``layout`` (mask: "valid"/"occupied" from their labels) and read back."""
    taps = {"feats": "volume_features", "logits": "voxel_logits"}
    tensors, kept, meta = {}, [], None
    for i in range(2):
        out, labels = _outputs(i)
        valid = labels != 255
        mask = {"all": None, "valid": valid, "occupied": valid & (labels != 0)}[layout.get("voxels", "all")]
        meta = meta or tap_layout(out, taps, None if mask is None else SHAPE, layout.get("topk"))
        tensors.update(sample_tensors(out, taps, f"{i}:0", mask=mask, topk=layout.get("topk"),
                                      precision=getattr(torch, layout.get("precision", "float32"))))
        kept.append((out, mask))
    entry = write_shard(folder, 0, tensors, {"count": 2})
    manifest = {"format": FORMAT, "taps": meta, "samples": ["a", "b"], "shard": 16, "draws": 1,
                "shards": [entry | {"first": 0}]}
    (folder / MANIFEST).write_text(json.dumps(manifest))
    return TeacherOutputs(folder), kept


@pytest.mark.parametrize("precision", ["float16", "bfloat16"])
def test_a_narrower_precision_reads_back_each_value_rounded_once(tmp_path, precision) -> None:
    reader, kept = _store(tmp_path, {"precision": precision})
    got = reader.batch(["a", "b"], [0, 0], torch.device("cpu"))
    for tap in ("logits", "feats"):
        want = torch.cat([o[tap] for o, _ in kept]).to(getattr(torch, precision)).float()
        assert got[tap].dtype == torch.float32 and torch.equal(got[tap], want)
    exact, _ = _store(_folder(tmp_path, "exact"), {})
    assert exact.manifest["shards"][0]["bytes"] > reader.manifest["shards"][0]["bytes"] * 1.8  # about half


@pytest.mark.parametrize("voxels", ["valid", "occupied"])
def test_a_masked_store_keeps_the_masks_voxels_exactly_and_reads_the_others_as_zero(tmp_path, voxels) -> None:
    reader, kept = _store(tmp_path, {"voxels": voxels})
    got = reader.batch(["b", "a"], [0, 0], torch.device("cpu"))  # in any order
    for row_of, (out, mask) in ((1, kept[0]), (0, kept[1])):
        for tap in ("logits", "feats"):
            row = got[tap][row_of]
            assert torch.equal(row[:, mask], out[tap][0][:, mask])
            assert bool((row[:, ~mask] == 0).all()) and bool((~mask).any())


def test_a_topk_store_keeps_the_k_largest_scores_and_the_rests_mass_spread_evenly(tmp_path) -> None:
    k = 2
    reader, kept = _store(tmp_path, {"topk": k})
    got = reader.batch(["a", "b"], [0, 0], torch.device("cpu"))
    assert torch.equal(got["feats"], torch.cat([o["feats"] for o, _ in kept]))  # features are not class scores
    for b, (out, _) in enumerate(kept):
        z, r = out["logits"][0].double(), got["logits"][b].double()
        for x, y, w in ((x, y, w) for x in range(SHAPE[0]) for y in range(SHAPE[1]) for w in range(SHAPE[2])):
            scores = [float(v) for v in z[:, x, y, w]]  # the naive softmax, voxel by voxel
            total = sum(math.exp(s) for s in scores)
            p = [math.exp(s) / total for s in scores]
            top = sorted(range(C), key=lambda c: -scores[c])[:k]
            q = torch.softmax(r[:, x, y, w], 0)
            for c in range(C):
                want = p[c] if c in top else (1 - sum(p[t] for t in top)) / (C - k)
                assert abs(float(q[c]) - want) < 1e-6
    exact, _ = _store(_folder(tmp_path, "exact"), {})
    assert reader.manifest["shards"][0]["bytes"] < 0.7 * exact.manifest["shards"][0]["bytes"]


@pytest.fixture(scope="module", autouse=True)
def raw_logits():
    """A plug-in term that reads the teacher's class scores themselves (an MSE), declaring nothing."""
    from distilkit.objectives.base import MultiTapObjective, register_objective
    from distilkit.registry import OBJECTIVES, NoParams

    class RawLogits(MultiTapObjective):
        Params = NoParams
        CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}

        def compute(self, taps, batch):
            return ((taps["student"] - taps["teacher"]) ** 2).mean()

    register_objective("test-raw-logits", RawLogits, description="test: MSE of logits", paper="tests",
                       equation="mean (s - t)^2", shapes="voxel logits")
    yield
    OBJECTIVES.remove("test-raw-logits")


@pytest.mark.parametrize("store, words", [
    ({"topk": 20}, r"topk: topk 20 keeps every one of the data's \d+ classes"),
    ({"voxels": "valid"}, r"voxels: distill\[0\] \(dskd\) reads|voxels: distill\[0\] \(kd\) reads"),
    ({"topk": 3}, r"topk: distill\[0\] \(test-raw-logits\) reads the teacher's 'logits' scores themselves"),
])
def test_validate_refuses_a_layout_that_drops_what_a_term_reads(store, words) -> None:
    from distilkit.engine.assemble.resolve import resolve

    recipe = tiny_recipe(steps=1)
    student = recipe["stages"]["student"]
    student["teacher"] = {"from": "teacher", "store": store}
    if "voxels" in store:
        student["distill"] = [{"name": "kd", "params": {"voxels": "all"}}]
    elif store["topk"] == 3:
        student["distill"] = [{"name": "test-raw-logits"}]
    else:
        student["distill"] = [{"name": "kd"}]
    with pytest.raises(RecipeError, match=r"stages\.student\.teacher\.store\." + words):
        resolve(recipe_from_dict(recipe))


def test_validate_accepts_the_layouts_a_terms_reads_allow() -> None:
    from distilkit.engine.assemble.resolve import resolve

    recipe = tiny_recipe(steps=1)
    recipe["stages"]["student"]["teacher"] = {"from": "teacher", "store": {"voxels": "valid", "topk": 4,
                                                                          "precision": "bfloat16"}}
    recipe["stages"]["student"]["distill"] = [{"name": "kd"}, {"name": "dist"}]
    store = resolve(recipe_from_dict(recipe)).stages["student"].spec.teacher.store  # no RecipeError: accepted
    assert (store.voxels, store.topk, store.precision, store.exact) == ("valid", 4, "bfloat16", False)


def _stored_only(shard: int = 1) -> dict:
    recipe = tiny_recipe(steps=1)
    recipe["stages"]["student"]["teacher"] = {"from": "teacher", "store": {"shard": shard}}
    return recipe


def test_processes_building_one_store_claim_disjoint_shards_and_no_wait_names_the_held_one(tmp_path,
                                                                                           monkeypatch) -> None:
    """Another process holds shard 0 (its lock taken here): this build computes shard 1 only, and with --no-wait
    stops naming shard 0 instead of waiting; once the holder lets go, the next build computes shard 0 alone."""
    import distilkit.engine.train.teacher_store as ts

    recipe = recipe_from_dict(_stored_only())
    Pipeline(recipe, tmp_path / "runs", quiet=True).run(only=["teacher"])
    computed = []
    real = ts._Build._shard
    monkeypatch.setattr(ts._Build, "_shard", lambda self, s: computed.append(s) or real(self, s))
    key, _ = _key(recipe, tmp_path)
    locks = tmp_path / "runs" / "tiny" / ".locks" / f"teacher-store-{key}"
    locks.mkdir(parents=True)
    fd = os.open(locks / "shard-00000.lock", os.O_RDWR | os.O_CREAT)
    fcntl.flock(fd, fcntl.LOCK_EX)  # another builder, busy with shard 0
    try:
        with pytest.raises(RunLockedError, match=r"shard 0 of the teacher store is being built by another"):
            Pipeline(recipe, tmp_path / "runs", quiet=True).run(wait=False)
        assert computed == [1]
    finally:
        os.close(fd)  # the other builder died: the kernel let go of its lock
    Pipeline(recipe, tmp_path / "runs", quiet=True).run(wait=False)
    assert computed == [1, 0]
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    assert store.name == f"teacher-store-{key}" and len(json.loads((store / MANIFEST).read_text())["shards"]) == 2


def _key(recipe, tmp_path) -> tuple[str, dict]:
    """The store key of the recipe's student stage, as its run computes it."""
    from distilkit.engine.train.stage import StageRun
    from distilkit.engine.train.teacher_store import store_key, store_taps

    pipe = Pipeline(recipe, tmp_path / "runs", quiet=True)
    run = StageRun(pipe, "student", pipe.run_dir("student"), None)
    return store_key(run, store_taps(run.stage))


def test_a_student_from_a_masked_store_equals_the_live_one_where_its_terms_read_only_those_voxels(tmp_path) -> None:
    """KD over the valid voxels reads nothing a valid-voxel store drops: its student is the live one's bits."""
    recipe = tiny_recipe(steps=2)
    live = recipe["stages"]["student"]
    live["distill"] = [{"name": "kd", "params": {"voxels": "valid"}}]
    stored = copy.deepcopy(live)
    stored["teacher"] = {"from": "teacher", "store": {"voxels": "valid"}}
    recipe["stages"]["student_stored"] = stored
    results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()}
    from distilkit.weights import load_checkpoint

    a, b = (load_checkpoint(results[n].run_dir / "checkpoints" / "last.pt")["student"]
            for n in ("student", "student_stored"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    taps = json.loads((store / MANIFEST).read_text())["taps"]
    assert any(t.get("masked") for t in taps.values())


def test_loader_workers_read_the_store_and_the_student_is_the_same_bits(tmp_path) -> None:
    """train.workers: 1 — the worker process reads each batch's teacher rows with the batch (WithTeacherOutputs)."""
    from distilkit.engine.store.teacher_outputs import TeacherOutputs
    from distilkit.weights import load_checkpoint

    log = tmp_path / "reads"  # the processes that read (a worker's appends are its own: a file is shared)
    real = TeacherOutputs.batch

    def batch(self, *a):
        with open(log, "a") as f:
            f.write(f"{os.getpid()}\n")
        return real(self, *a)
    recipe = tiny_recipe(steps=2)
    stored = copy.deepcopy(recipe["stages"]["student"])
    stored["teacher"] = {"from": "teacher", "store": True}
    stored["train"]["workers"] = 1
    recipe["stages"]["student_stored"] = stored
    TeacherOutputs.batch = batch
    try:
        results = {r.name: r for r in Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run()}
    finally:
        TeacherOutputs.batch = real
    a, b = (load_checkpoint(results[n].run_dir / "checkpoints" / "last.pt")["student"]
            for n in ("student", "student_stored"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    reads = [int(x) for x in log.read_text().split()]
    assert os.getpid() in reads  # the first batch (sizing the terms) is read here ...
    assert any(pid != os.getpid() for pid in reads)  # ... the training batches by the worker


def test_validate_estimates_a_stored_student_without_its_teacher_and_the_stores_disk(tmp_path) -> None:
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.engine.memory.estimate import estimate_stage

    recipe = tiny_recipe(steps=1)
    live = resolve(recipe_from_dict(recipe))
    recipe["stages"]["student"]["teacher"] = {"from": "teacher", "store": True}
    stored = resolve(recipe_from_dict(recipe))
    a, b = estimate_stage(live, "student"), estimate_stage(stored, "student")
    assert a.store is None and b.store is not None and b.high < a.high  # the teacher's weights and forward are gone
    assert b.store[0] > 0 and "store of about" in b.line()


def test_a_build_killed_with_sigkill_resumes_with_its_finished_shards(tmp_path) -> None:
    """A process killed (SIGKILL: no clean-up at all) while computing its second shard: its shard locks die with it,
    the next run keeps the first shard as written and builds the second."""
    import signal
    import subprocess
    import sys

    recipe = _stored_only()
    path = tmp_path / "recipe.json"
    path.write_text(json.dumps(recipe))
    script = f"""
import json, os, signal
import distilkit.engine.train.teacher_store as ts
from distilkit.engine.train.pipeline import Pipeline
from distilkit.recipe import recipe_from_dict
real, calls = ts.write_shard, []
def once(*a):
    if calls:
        os.kill(os.getpid(), signal.SIGKILL)
    calls.append(1)
    return real(*a)
ts.write_shard = once
Pipeline(recipe_from_dict(json.loads(open({str(path)!r}).read())), {str(tmp_path / 'runs')!r}, quiet=True).run()
"""
    done = subprocess.run([sys.executable, "-c", script], cwd=os.getcwd(), capture_output=True, timeout=300)
    assert done.returncode == -signal.SIGKILL, done.stderr.decode()[-2000:]
    (store,) = (tmp_path / "runs" / "tiny").glob("teacher-store-*")
    assert (store / "shard-00000.safetensors").is_file() and not (store / MANIFEST).exists()
    first = (store / "shard-00000.safetensors").stat().st_mtime_ns
    Pipeline(recipe_from_dict(recipe), tmp_path / "runs", quiet=True).run(wait=False)  # no lock is left held
    assert (store / "shard-00000.safetensors").stat().st_mtime_ns == first
    assert [s["count"] for s in json.loads((store / MANIFEST).read_text())["shards"]] == [1, 1]
