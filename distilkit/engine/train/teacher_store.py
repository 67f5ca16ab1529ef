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
another. The layout (:class:`~distilkit.recipe.store.StoreSpec`: precision, voxels, top-k) and the labels that
choose a masked layout's voxels are in the key too.

The build is shared: each process that needs the store (the parallel students of a sweep's ``--jobs``, torchrun's
ranks, a cluster's array tasks on a shared folder) claims shards one at a time with an ``flock`` on
``.locks/teacher-store-<key>/shard-NNNNN.lock``, builds those no one holds, then waits for the others' (building
any whose holder died: the kernel drops a dead process's lock); so N processes build disjoint shards, and an
interrupted build, or one whose shard was deleted, redoes only the missing shards. One process writes the
manifest last (under the store's own lock), after measuring on the first batch whether the teacher computes a
sample in a batch as it does alone.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any, Callable

import torch

from distilkit import __version__
from distilkit.engine.store.teacher_outputs import (FORMAT, MANIFEST, TeacherOutputs, batch_difference,
                                                   finished_shard, sample_tensors, shard_name, whole, write_shard)


def store_taps(stage: Any) -> dict[str, str]:
    """The teacher taps the stage's distillation terms read, with their kinds (what a store holds)."""
    out: dict[str, str] = {}
    for term in stage.distill:
        for role, tap in term.taps.items():
            if role in term.card.TEACHER_ROLES:
                out[tap] = stage.teacher.taps[tap]
    return dict(sorted(out.items()))


def store_labels(stage: Any) -> str:
    """The batch field whose labels choose a masked store's voxels: the one by which the stage's terms that read a
    dense teacher tap choose theirs (:func:`~distilkit.engine.assemble.store_checks.mask_labels`; ``validate`` refuses
    terms that differ; default ``voxel_target``)."""
    from distilkit.engine.assemble.store_checks import mask_labels

    fields = mask_labels(stage.distill, stage.teacher.taps if stage.teacher is not None else {})
    return next(iter(fields)) if len(fields) == 1 else "voxel_target"


def keep_mask(stage: Any, batch: Any, info: Any) -> torch.Tensor | None:
    """The (X, Y, Z) voxels a masked store keeps of a batch of one, from its labels (None: every voxel)."""
    voxels = stage.spec.teacher.store.voxels
    if voxels == "all":
        return None
    labels = batch.field(store_labels(stage))[0]
    keep = labels != info.classes.ignore_index
    return keep & (labels != 0) if voxels == "occupied" else keep


def stored_bytes(stage: Any, outputs: dict[str, Any], batch: Any, info: Any) -> int:
    """The bytes one sample's teacher outputs (a batch of one) take in the stage's store layout (before the
    safetensors header): what ``validate`` scales to its disk estimate."""
    store = stage.spec.teacher.store
    tensors = sample_tensors(outputs, store_taps(stage), "0:0", mask=keep_mask(stage, batch, info), topk=store.topk,
                             precision=getattr(torch, store.precision))
    return sum(t.numel() * t.element_size() for t in tensors.values())


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
    layout = spec.teacher.store
    if not layout.exact:  # the lossy layouts (the exact one keeps its key of before)
        what["layout"] = {"voxels": layout.voxels, "topk": layout.topk,
                          "labels": store_labels(stage) if layout.voxels != "all" else None}
    return hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:12], what


def ensure_store(run: Any, train_set: Any, augmentation: Any) -> TeacherOutputs:
    """The stage's store, built first where it is not finished (shards shared with the other processes building it,
    see the module); ``augmentation``: the stage's (:class:`~distilkit.data.augment.Augmentation`) or None."""
    taps = store_taps(run.stage)
    key, what = store_key(run, taps)
    folder = run.pipeline.root / f"teacher-store-{key}"
    if not whole(folder):  # not built, interrupted, or a shard deleted since: (re)build what is missing
        _Build(run, folder, train_set, augmentation, taps, key, what).build()
    return TeacherOutputs(folder)


class _Build:
    """One process's part of building a store: the shards it claims, the manifest if it is the one to write it."""

    def __init__(self, run: Any, folder: Path, train_set: Any, augmentation: Any, taps: dict[str, str], key: str,
                 what: dict[str, Any]) -> None:
        self.run, self.folder, self.train_set, self.augmentation = run, folder, train_set, augmentation
        self.taps, self.key, self.what = taps, key, what
        self.spec = run.stage.spec.teacher.store
        self.draws = augmentation.draws if augmentation is not None else 1
        self.per_shard, self.n = self.spec.shard, len(train_set)
        self.counts = [min(self.per_shard, self.n - first) for first in range(0, self.n, self.per_shard)]
        self.locks = run.pipeline.root / ".locks" / folder.name
        self.wait = getattr(run.pipeline, "wait", True)
        self._teacher: Any = None
        self._done: dict[int, dict[str, Any]] = {}  # shards found whole (their checksums read once)
        self.built = 0  # samples x draws this process computed

    @property
    def teacher(self) -> Any:
        """The frozen teacher, loaded when this process first has something to compute."""
        if self._teacher is None:
            from distilkit.engine.assemble.runs import load_run

            self._teacher = load_run(self.run.upstream("teacher"), model=self.run.stage.teacher, info=self.run.info,
                                     device=self.run.device, role="teacher")
            self._teacher.eval()
        return self._teacher

    def _autocast(self) -> Any:  # the teacher runs under the stage's autocast, as it does live
        from distilkit.engine.train.precision import autocast

        return autocast(self.run.device, self.run.stage.spec.train.precision)

    def finished(self, s: int) -> dict[str, Any] | None:
        """Shard ``s``'s record where it is whole (checked once: its SHA-256 read through)."""
        if s not in self._done:
            done = finished_shard(self.folder, s)
            if done is None or done.get("count") != self.counts[s]:
                return None
            self._done[s] = done
        return self._done[s]

    def build(self) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        from distilkit.engine.store.lock import lock_path, stage_lock

        start = time.perf_counter()
        self.folder.mkdir(parents=True, exist_ok=True)
        console = self.run.pipeline.console
        with Progress(TextColumn(f"[cyan]teacher store[/] {self.folder.name}"), BarColumn(), MofNCompleteColumn(),
                      TimeRemainingColumn(), console=console, transient=True) as progress:
            task = progress.add_task("store", total=len(self.counts))
            waiting = []
            for s in range(len(self.counts)):  # the shards no one holds, built here
                if self.finished(s) is None and not self._claim(s, block=False, say=progress.console.print):
                    waiting.append(s)  # another process is building it
                progress.update(task, completed=s + 1 - len(waiting))
            for s in waiting:  # then the others', once their builders let go (a dead one's, built here)
                self._claim(s, block=True, say=progress.console.print)
                progress.advance(task)
        with stage_lock(lock_path(self.run.pipeline.root, self.folder.name), wait=True):
            if not whole(self.folder):
                self._manifest(start)

    def _claim(self, s: int, block: bool, say: Callable[..., None] = lambda *a, **k: None) -> bool:
        """Shard ``s`` built under its lock unless it is finished by then; False: held by another (``block`` off).
        ``say``: where the line that it waits for another process goes (a progress bar's console)."""
        import fcntl

        from distilkit.errors import RunLockedError

        self.locks.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.locks / f"shard-{s:05d}.lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                if not block:
                    return False
                if not self.wait:
                    raise RunLockedError(f"{self.folder}: shard {s} of the teacher store is being built by another "
                                         "distilkit run; wait for it (without --no-wait)") from None
                say(f"{self.folder.name}: waiting for shard {s}, built by another run", highlight=False)
                fcntl.flock(fd, fcntl.LOCK_EX)
            if self.finished(s) is None:
                self._shard(s)
            return True
        finally:
            os.close(fd)  # releases the lock

    def _shard(self, s: int) -> None:
        """Compute and write shard ``s``: each of its samples under every draw, alone in a batch of one."""
        from distilkit.engine.store.teacher_outputs import tap_layout

        tensors: dict[str, torch.Tensor] = {}
        first = s * self.per_shard
        layout = None
        for i in range(first, first + self.counts[s]):
            sample = self.train_set[i]
            for d in range(self.draws):
                seen = self.augmentation.apply(sample, d) if self.augmentation is not None else sample
                batch = self.run.prepare_training(self.run.pipeline.collate([seen]))  # with the aux models' inputs
                with torch.no_grad(), self._autocast():
                    out = self.teacher(batch)
                mask = self._mask(batch)
                layout = layout or tap_layout(out, self.taps, None if mask is None else tuple(mask.shape),
                                              self.spec.topk)
                tensors.update(sample_tensors(out, self.taps, f"{i}:{d}", mask=mask, topk=self.spec.topk,
                                              precision=getattr(torch, self.spec.precision)))
                self.built += 1
        write_shard(self.folder, s, tensors, {"count": self.counts[s], "taps": layout})

    def _mask(self, batch: Any) -> torch.Tensor | None:
        return keep_mask(self.run.stage, batch, self.run.info)

    def _manifest(self, start: float) -> None:
        from distilkit.files import atomic_write_text

        shards, layout = [], None
        for s in range(len(self.counts)):
            if not (self.folder / shard_name(s)).is_file():  # deleted since this process saw it whole
                self._done.pop(s, None)
            done = self.finished(s)
            if done is None:  # deleted or altered since it was built: built again here
                self._claim(s, block=True)  # quietly
                done = self.finished(s)
                assert done is not None
            layout = layout or done.get("taps")
            shards.append({k: v for k, v in done.items() if k != "taps"} | {"first": s * self.per_shard})
        check = self._batch_check()
        manifest = {"format": FORMAT, "key": self.key, "built_from": self.what, "taps": layout or {},
                    "draws": self.draws, "batch_check": check, "shard": self.per_shard,
                    "samples": [str(self.train_set.sample_id(i)) for i in range(self.n)], "shards": shards,
                    "bytes": sum(e["bytes"] for e in shards)}
        atomic_write_text(self.folder / MANIFEST, json.dumps(manifest, indent=1))
        self._teacher = None
        n, draws, size = self.n, self.draws, manifest["bytes"]
        console = self.run.pipeline.console
        console.print(
            f"teacher store {self.folder.name}: {n} samples x {draws} draw{'s' if draws > 1 else ''}, "
            f"{size / 2 ** 20:.1f} MiB in {len(shards)} shard{'s' if len(shards) > 1 else ''} "
            f"({size / max(1, n * draws) / 2 ** 20:.2f} MiB a sample); {self.built} computed here in "
            f"{time.perf_counter() - start:.1f} s", highlight=False, soft_wrap=True)
        if check and (check["max_difference"] or 0) > 0:
            console.print(
                f"[yellow]teacher store:[/] the teacher computes a sample in a batch of {check['batch']} differently "
                f"from the sample alone (largest difference {check['max_difference']:.3g}, tap {check['tap']!r}): a "
                f"student trained from {self.folder.name} differs from one trained with the live teacher in the last "
                "bits (with train.batch_size 1 they are the same)", highlight=False, soft_wrap=True)

    def _batch_check(self) -> dict[str, Any] | None:
        """Whether the stored rows are the live teacher's at the stage's batch size: its forward on the first batch
        against its forward on each of those samples alone (None: a batch of one, where they are the same by
        construction)."""
        run, train_set = self.run, self.train_set
        size = min(max(1, run.stage.spec.train.batch_size // run.world.size), len(train_set))  # this process's
        if size < 2:
            return None
        samples = [train_set[i] for i in range(size)]
        try:  # a measurement: what it cannot measure (memory) it says, and the store stands
            with torch.no_grad(), self._autocast():
                together = self.teacher(run.prepare_training(run.pipeline.collate(samples)))
                alone = [self.teacher(run.prepare_training(run.pipeline.collate([s]))) for s in samples]
            worst, tap = batch_difference(together, alone, self.taps)
        except Exception as exc:  # noqa: BLE001
            return {"batch": size, "max_difference": None, "error": f"{type(exc).__name__}: {exc}"}
        return {"batch": size, "max_difference": worst, "tap": tap}


__all__ = ["ensure_store", "keep_mask", "store_key", "store_labels", "store_taps", "stored_bytes"]
