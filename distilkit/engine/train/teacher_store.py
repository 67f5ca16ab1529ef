"""The teacher run once (``teacher: {from: ..., store: true}``): the frozen teacher's outputs over the training split,
under every draw of ``train.augment``'s finite group, written to a store (:mod:`distilkit.engine.store.teacher_outputs`)
that every student sharing them reads instead of running the teacher.

The store's key hashes what its content depends on and nothing else: the teacher's adapter, code version, parameters,
the recorded taps it stores and the SHA-256 of its weights (their values, not the file's bytes); the data's
fingerprint (:func:`~distilkit.engine.store.identity.data_fingerprint`) and the dataset's code versions; the labels a
stage overlays and the auxiliary models whose predictions become inputs (their runs' identities); the taps the
stage's terms read with their kinds; the augmentation; the training precision (the teacher runs under the stage's
autocast, with the auxiliary models' inputs, as it does live); the stored precision and the format. So the students
of a sweep that share a teacher, data, taps and augmentation read one store, and a changed teacher or tap builds
another. The build holds a lock on the store (a sweep's parallel students wait for one build), writes shard by shard
(an interrupted build, or one whose shard was deleted, resumes at the first missing shard), and writes the manifest
last; it then measures, on the first batch, whether the teacher computes a sample in a batch as it does alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from pathlib import Path
from typing import Any

import torch

from distilkit import __version__
from distilkit.engine.store.teacher_outputs import (FORMAT, MANIFEST, TeacherOutputs, batch_difference,
                                                   finished_shard, sample_tensors, tap_layout, whole, write_shard)


def store_taps(stage: Any) -> dict[str, str]:
    """The teacher taps the stage's distillation terms read, with their kinds (what a store holds)."""
    out: dict[str, str] = {}
    for term in stage.distill:
        for role, tap in term.taps.items():
            if role in term.card.TEACHER_ROLES:
                out[tap] = stage.teacher.taps[tap]
    return dict(sorted(out.items()))


def weights_digest(path: Path, model: Any) -> str:
    """SHA-256 of a teacher's weights as its adapter reads them (names, dtypes, shapes, values) — not of the file,
    whose other records (a time, a path) differ between two runs that trained the same weights."""
    digest = hashlib.sha256()
    for name, value in sorted(model.cls.read_weights(str(path)).items()):
        digest.update(f"{name}|{value.dtype}|{tuple(value.shape)}|".encode())
        digest.update(value.detach().cpu().contiguous().numpy().tobytes() if value.dtype != torch.bfloat16
                      else value.detach().cpu().float().numpy().tobytes())
    return digest.hexdigest()


def store_key(run: Any, taps: dict[str, str]) -> tuple[str, dict[str, Any]]:
    """(the store's key, what it hashes) for a stage run (:class:`~distilkit.engine.train.stage.StageRun`)."""
    from distilkit.engine.store.identity import data_fingerprint

    from distilkit.engine.store.identity import code_versions

    stage, spec = run.stage, run.stage.spec
    teacher, hashes = stage.teacher, run.pipeline.hashes
    versions = code_versions(run.pipeline.resolved, stage)
    labels = spec.labels if spec.labels is not None and "train" in spec.labels.splits else None
    what = {
        "format": FORMAT, "distilkit": __version__,
        "teacher": {"adapter": teacher.adapter, "version": getattr(teacher.card, "VERSION", 1),
                    "params": teacher.params.model_dump(mode="json"),
                    "taps": {k: v.model_dump(mode="json") for k, v in sorted(teacher.hooks.items()) if k in taps},
                    "weights": weights_digest(run.upstream("teacher"), teacher), "mode": spec.teacher.mode},
        # the data the teacher reads: its fingerprint and code versions, the labels a stage overlays, the auxiliary
        # models whose predictions become its inputs
        "data": data_fingerprint(run.pipeline.resolved, stage), "split": "train",
        "data_versions": {k: versions[k] for k in ("dataset", "fields") if k in versions},
        "labels": None if labels is None else {**labels.model_dump(mode="json", by_alias=True),
                                               "run": hashes.get(labels.from_)},
        "aux": [{"name": a.name, "run": hashes.get(a.stage), "which": a.which, "inputs": a.inputs,
                 "training": a.training} for a in stage.aux],
        "taps": taps,
        "augment": spec.train.augment.model_dump(mode="json") if spec.train.augment is not None else None,
        "precision": spec.train.precision, "store_precision": spec.teacher.store.precision,
    }
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:12], what


def ensure_store(run: Any, train_set: Any, augmentation: Any) -> TeacherOutputs:
    """The stage's store, built first where it is not finished (under its lock, resuming at the first unfinished
    shard); ``augmentation``: the stage's (:class:`~distilkit.data.augment.Augmentation`) or None."""
    from distilkit.engine.store.lock import lock_path, stage_lock

    taps = store_taps(run.stage)
    key, what = store_key(run, taps)
    folder = run.pipeline.root / f"teacher-store-{key}"
    if not whole(folder):  # not built, interrupted, or a shard deleted since: (re)build what is missing
        with stage_lock(lock_path(run.pipeline.root, folder.name),
                        on_wait=lambda holder: run.pipeline.console.print(
                            f"[yellow]{folder.name} is being built by another run ({holder}); waiting[/]")):
            if not whole(folder):
                (folder / MANIFEST).unlink(missing_ok=True)
                _build(run, folder, train_set, augmentation, taps, key, what)
    return TeacherOutputs(folder)


def _build(run: Any, folder: Path, train_set: Any, augmentation: Any, taps: dict[str, str], key: str,
           what: dict[str, Any]) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from distilkit.engine.assemble.runs import load_run
    from distilkit.files import atomic_write_text

    start = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    spec = run.stage.spec
    teacher = load_run(run.upstream("teacher"), model=run.stage.teacher, info=run.info, device=run.device,
                       role="teacher")
    teacher.eval()
    draws = augmentation.draws if augmentation is not None else 1
    per_shard = spec.teacher.store.shard
    n = len(train_set)
    shards: list[dict[str, Any]] = []
    layout: dict[str, Any] | None = None
    precision = spec.train.precision  # the teacher runs under the stage's autocast, as it does live

    def autocast() -> Any:
        if precision == "fp32":
            return contextlib.nullcontext()
        return torch.autocast(run.device.type, dtype=torch.bfloat16 if precision == "bf16" else torch.float16)
    with Progress(TextColumn(f"[cyan]teacher store[/] {folder.name}"), BarColumn(), MofNCompleteColumn(),
                  TimeRemainingColumn(), console=run.pipeline.console, transient=True) as progress:
        task = progress.add_task("store", total=n * draws)
        for s, first in enumerate(range(0, n, per_shard)):
            count = min(per_shard, n - first)
            done = finished_shard(folder, s)
            if done is not None and done.get("count") == count:  # kept from an interrupted build
                layout = layout or done.get("taps")
                shards.append({k: v for k, v in done.items() if k != "taps"} | {"first": first})
                progress.advance(task, count * draws)
                continue
            tensors: dict[str, torch.Tensor] = {}
            for i in range(first, first + count):
                sample = train_set[i]
                for d in range(draws):
                    seen = augmentation.apply(sample, d) if augmentation is not None else sample
                    batch = run.prepare_training(run.pipeline.collate([seen]))  # with the aux models' inputs
                    with torch.no_grad(), autocast():
                        out = teacher(batch)
                    layout = layout or tap_layout(out, taps)
                    tensors.update(sample_tensors(out, taps, f"{i}:{d}"))
                    progress.advance(task)
            entry = write_shard(folder, s, tensors, {"count": count, "taps": layout})
            shards.append({k: v for k, v in entry.items() if k != "taps"} | {"first": first})
    check = _batch_check(run, teacher, train_set, taps, autocast)
    manifest = {"format": FORMAT, "key": key, "built_from": what, "taps": layout or {}, "draws": draws,
                "batch_check": check,
                "shard": per_shard, "samples": [str(train_set.sample_id(i)) for i in range(n)], "shards": shards,
                "bytes": sum(e["bytes"] for e in shards)}
    atomic_write_text(folder / MANIFEST, json.dumps(manifest, indent=1))
    del teacher
    run.pipeline.console.print(
        f"teacher store {folder.name}: {n} samples x {draws} draw{'s' if draws > 1 else ''}, "
        f"{manifest['bytes'] / 2 ** 20:.1f} MiB in {len(shards)} shard{'s' if len(shards) > 1 else ''} "
        f"({manifest['bytes'] / max(1, n * draws) / 2 ** 20:.2f} MiB a sample), {time.perf_counter() - start:.1f} s",
        highlight=False, soft_wrap=True)
    if check and (check["max_difference"] or 0) > 0:
        run.pipeline.console.print(
            f"[yellow]teacher store:[/] the teacher computes a sample in a batch of {check['batch']} differently from "
            f"the sample alone (largest difference {check['max_difference']:.3g}, tap {check['tap']!r}): a student "
            f"trained from {folder.name} differs from one trained with the live teacher in the last bits (with "
            f"train.batch_size 1 they are the same)", highlight=False, soft_wrap=True)


def _batch_check(run: Any, teacher: Any, train_set: Any, taps: dict[str, str], autocast: Any) -> dict[str, Any] | None:
    """Whether the stored rows are the live teacher's at the stage's batch size: its forward on the first batch
    against its forward on each of those samples alone (None: a batch of one, where they are the same by
    construction)."""
    size = min(max(1, run.stage.spec.train.batch_size // run.world.size), len(train_set))  # this process's batch
    if size < 2:
        return None
    samples = [train_set[i] for i in range(size)]
    try:  # a measurement: what it cannot measure (memory) it says, and the store stands
        with torch.no_grad(), autocast():
            together = teacher(run.prepare_training(run.pipeline.collate(samples)))
            alone = [teacher(run.prepare_training(run.pipeline.collate([s]))) for s in samples]
        worst, tap = batch_difference(together, alone, taps)
    except Exception as exc:  # noqa: BLE001
        return {"batch": size, "max_difference": None, "error": f"{type(exc).__name__}: {exc}"}
    return {"batch": size, "max_difference": worst, "tap": tap}


__all__ = ["ensure_store", "store_key", "store_taps"]
