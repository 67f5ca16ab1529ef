"""``distilkit bench teacher-store``: what a teacher store (issue 58) saves against running the teacher live, for the
distillation stage of each paper recipe (``recipes/paper/*.yaml``) whose terms read teacher taps — SCPNet's and
JS3C-Net's DSKD (sparse completion features), Scribble2Scene's RGO²D (VoxFormer's logits and image features);
ScoreLiDAR's is a line under the table (VSD calls the teacher itself). The recipe's teacher (``size: paper``, random
weights) runs on the synthetic streets at the papers' sizes (:func:`~distilkit.bench.fixtures.data_sizes`; ``--quick``
a quarter, ``test=True`` the tests' sizes with the ``size: tiny`` stand-ins), whose labels choose the masked layouts'
voxels as a store's build does. A family's first row: the teacher's forward on one sample (batch of one, ``no_grad``,
the stage's autocast; the median of up to :data:`REPEAT` timed forwards after a warm-up, fewer where one is slow).
Then one row per layout of :data:`LAYOUTS`: the stage's taps of :data:`SAMPLES` samples stored as the build stores
them (``sample_tensors``, ``write_shard``, a manifest) and read back through ``TeacherOutputs.batch`` one sample a
batch — the median read a sample over :data:`READS` reads after the first (``fast ms``; the first, which opens the
shard and checks its SHA-256: ``1st read ms``), bytes a sample on disk, each tap's largest absolute difference from
the live teacher (masked layouts: inside the mask; top-k: of the softmax probabilities), each distillation term's
value with the read-back outputs against its value with the live ones (the same outputs of the stage's student, with
random weights; absolute and relative: :mod:`~distilkit.bench.store_compare`), forward time over read time, and
whether ``validate`` accepts the layout for the stage.
"""

from __future__ import annotations

import dataclasses
import functools
import gc
import json
import shutil
import statistics
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import torch
from torch import Tensor

from distilkit.bench.base import (Case, Skipped, peak_bytes, peak_reset, register, resident_bytes, scratch_dir,
                                  time_left)
from distilkit.bench.fixtures import PAPER_RECIPES, paper_recipe
from distilkit.bench.store_compare import difference, mask_of, term_differences, values

FAMILIES = {"scpnet": "SCPNet", "js3cnet": "JS3C-Net", "voxformer": "VoxFormer", "lidiff": "LiDiff"}
SAMPLES = 2  # samples stored per layout
REPEAT = 3  # timed forwards at most (after the warm-up)
FORWARD_BUDGET_S = 30.0  # fewer timed forwards where the warm-up says they would take longer than this
READS = 5  # timed reads of each sample after the first
LAYOUTS: dict[str, dict[str, Any]] = {
    "float32": {}, "float16": {"precision": "float16"}, "bfloat16": {"precision": "bfloat16"},
    "voxels valid": {"voxels": "valid"}, "voxels occupied": {"voxels": "occupied"},
    "topk 2": {"topk": 2}, "topk 4": {"topk": 4}}


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclasses.dataclass
class Subject:
    """A family's teacher run on :data:`SAMPLES` samples: what the layout rows store and compare against."""

    stage: Any  # the resolved stage
    info: Any  # its data's
    taps: dict[str, str]  # the teacher taps its terms read, with their kinds
    ids: list[str]  # the samples'
    outputs: list[dict[str, Any]]  # the live teacher's, per sample (batch of one)
    labels: list[Tensor]  # the (X, Y, Z) labels that choose the masked layouts' voxels
    forward_ms: float
    forward_peak: int | None
    timed: int  # forwards timed
    draws: int  # draws of train.augment a store holds each sample under
    bytes: dict[str, float] = dataclasses.field(default_factory=dict)  # layout -> bytes a sample (rows run)
    trainer: Any = None  # the stage's (its teacher dropped once the outputs are taken)
    batches: list[Any] = dataclasses.field(default_factory=list)  # the samples, prepared
    student: list[dict[str, Any]] = dataclasses.field(default_factory=list)  # the student's outputs (random weights)
    terms: list[dict[str, float]] = dataclasses.field(default_factory=list)  # each term's value, live teacher


_RESIDENT: dict[str, Subject] = {}  # the one family built, released before another is built
_FAILED: dict[str, str] = {}  # family -> why its teacher could not run (its rows are skipped with it)


def release() -> None:
    """Release the resident family (and, on CUDA, the allocator's cache)."""
    _RESIDENT.clear()
    gc.collect()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.empty_cache()


def resolved(name: str, device: torch.device, quick: bool, test: bool) -> Any:
    """Paper recipe ``name`` resolved on the synthetic streets at the bench's sizes (:func:`paper_recipe`;
    :data:`SAMPLES` training samples), its stages on ``device``; ``test``: every network at ``size: tiny``."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    path = str(PAPER_RECIPES / f"{name}.yaml")
    recipe = paper_recipe(name, quick, test, device.type, num_train=SAMPLES, tiny=test)
    return resolve(recipe_from_dict(recipe, path), path)


def build(name: str, stage_name: str, device: torch.device, quick: bool, test: bool) -> Subject:
    """The stage as its trainer builds it (teacher, student with random weights, terms sized on sample 0) on
    :data:`SAMPLES` samples: a warm-up forward of the teacher (sample 0's output), up to :data:`REPEAT` timed ones on
    the last sample (its output: the last); the student's outputs and each term's value with the live teacher's."""
    from distilkit.data.augment import Augmentation
    from distilkit.engine.memory.probe import probe_trainer
    from distilkit.engine.train.precision import autocast
    from distilkit.engine.train.teacher_store import store_labels, store_taps

    if time_left() <= 0:
        raise Skipped("the time limit ran out before its teacher ran")
    res = resolved(name, device, quick, test)
    trainer = probe_trainer(res, stage_name, res.data_params, scratch_dir("run-"))
    stage, info, train_set, teacher = trainer.stage, trainer.info, trainer.train_set, trainer.teacher
    batches = [trainer.prepare(trainer.collate([train_set[i]])) for i in range(SAMPLES)]
    taps, precision = store_taps(stage), stage.spec.train.precision

    def forward(i: int) -> dict[str, Any]:
        with torch.no_grad(), autocast(device, precision):
            return teacher(batches[i])

    t0 = time.perf_counter()
    outputs = [forward(0)]  # the warm-up
    _sync(device)
    warm_s = time.perf_counter() - t0
    timed = max(1, min(REPEAT, int(FORWARD_BUDGET_S / max(warm_s, 1e-9))))
    times, last = [], None
    peak_reset(device)
    base = resident_bytes(device)
    for k in range(timed):
        if time_left() <= 0:
            raise Skipped(f"the time limit ran out after {k} of its timed forwards")
        _sync(device)
        t0 = time.perf_counter()
        last = forward(SAMPLES - 1)
        _sync(device)
        times.append((time.perf_counter() - t0) * 1000)
    peak = peak_bytes(device, base)
    outputs += [forward(i) for i in range(1, SAMPLES - 1)] + [last]
    trainer.teacher = None  # the terms below read the outputs given them
    with torch.no_grad(), autocast(device, precision):
        student = [trainer.student(b) for b in batches]
    live = [values(trainer, s_out, t_out, b) for s_out, t_out, b in zip(student, outputs, batches)]
    labels = [b.field(store_labels(stage))[0].cpu() for b in batches]
    draws = Augmentation(stage.spec.train.augment, info.grid).draws if stage.spec.train.augment is not None else 1
    ids = [str(train_set.sample_id(i)) if hasattr(train_set, "sample_id") else str(i) for i in range(SAMPLES)]
    return Subject(stage, info, taps, ids, outputs, labels, statistics.median(times), peak, timed, draws,
                   trainer=trainer, batches=batches, student=student, terms=live)


def subject(key: str, make: Callable[[], Subject]) -> Subject:
    """The family built by ``make`` under ``key``: the resident one if it is ``key``'s, else a new one (the resident
    one released first). A build that fails skips each of the family's rows with its reason, built once."""
    from distilkit.engine.train.oom import is_out_of_memory

    if key in _FAILED:
        raise Skipped(_FAILED[key])
    if key not in _RESIDENT:
        release()
        try:
            _RESIDENT[key] = make()
        except Exception as exc:  # a family that cannot run here leaves the others to run
            release()
            if isinstance(exc, Skipped):
                why = str(exc)
            elif is_out_of_memory(exc):
                why = f"its teacher ran out of the device's memory ({str(exc).splitlines()[0][:200]})"
            else:
                traceback.print_exc()
                why = f"its teacher failed — {type(exc).__name__}: {str(exc)[:300]}"
            _FAILED[key] = why
            raise Skipped(why) from None
    return _RESIDENT[key]


def write_store(sub: Subject, spec: Any, folder: Path) -> list[Tensor | None]:
    """The subject's samples stored in ``spec``'s layout as one shard and a manifest; the masks used."""
    from distilkit.engine.store.teacher_outputs import FORMAT, MANIFEST, sample_tensors, tap_layout, write_shard

    dtype, ignore = getattr(torch, spec.precision), sub.info.classes.ignore_index
    tensors: dict[str, Tensor] = {}
    masks, layout = [mask_of(labels, spec.voxels, ignore) for labels in sub.labels], None
    for i, (out, mask) in enumerate(zip(sub.outputs, masks)):
        layout = layout or tap_layout(out, sub.taps, None if mask is None else tuple(mask.shape), spec.topk)
        tensors.update(sample_tensors(out, sub.taps, f"{i}:0", mask=mask, topk=spec.topk, precision=dtype))
    entry = write_shard(folder, 0, tensors, {"count": len(sub.ids), "taps": layout})
    shard = {k: v for k, v in entry.items() if k != "taps"} | {"first": 0}
    manifest = {"format": FORMAT, "taps": layout, "draws": 1, "shard": len(sub.ids), "samples": sub.ids,
                "shards": [shard], "bytes": entry["bytes"]}
    (folder / MANIFEST).write_text(json.dumps(manifest))
    return masks


def read_row(sub: Subject, layout: str, device: torch.device, case: Case) -> tuple[float, int | None, float]:
    """Store the subject's samples in ``layout``, read them back and fill the row (see the module)."""
    from distilkit.engine.assemble.store_checks import layout_problems
    from distilkit.engine.store.teacher_outputs import TeacherOutputs
    from distilkit.recipe.store import StoreSpec

    spec = StoreSpec(**LAYOUTS[layout])
    folder = scratch_dir("teacher-store-")
    try:
        masks = write_store(sub, spec, folder)
        size = sum(p.stat().st_size for p in folder.glob("shard-*.safetensors")) / len(sub.ids)
        store = TeacherOutputs(folder)  # a fresh reader: its first read opens and checks the shard
        _sync(device)
        t0 = time.perf_counter()
        for sid in sub.ids:
            store.batch([sid], [0], device)
        _sync(device)
        first = (time.perf_counter() - t0) * 1000 / len(sub.ids)
        times: list[float] = []
        peak_reset(device)
        base = resident_bytes(device)
        for _ in range(READS):
            if time_left() <= 0:
                raise Skipped("the time limit ran out during its reads")
            read: list[dict[str, Any]] = []
            for sid in sub.ids:
                _sync(device)
                t0 = time.perf_counter()
                read.append(store.batch([sid], [0], device))
                _sync(device)
                times.append((time.perf_counter() - t0) * 1000)
        peak = peak_bytes(device, base)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    worst = {tap: max(difference(live[tap], got[tap], store.taps[tap], mask)
                      for live, got, mask in zip(sub.outputs, read, masks)) for tap in sub.taps}
    terms = term_differences(sub, read)
    ms, sub.bytes[layout] = statistics.median(times), size
    reference = sub.bytes.get("float32")
    refused = layout_problems(spec, sub.stage.distill, sub.stage.teacher.taps, sub.info, "teacher.store")
    case.columns.update({
        "bytes/sample": f"{size / 2**20:,.2f} MiB" if size >= 2**20 else f"{size / 2**10:,.1f} KiB",
        "vs float32": f"{size / reference:.2f}×" if reference else "—",
        "1st read ms": f"{first:,.1f}", "max |Δ|": "; ".join(f"{tap} {d:.1e}" if d else f"{tap} 0"
                                                               for tap, d in worst.items()),
        "terms |Δ| (rel.)": "; ".join(f"{key[3:]} {d:.1e} ({r:.0e})" if d else f"{key[3:]} 0"
                                      for key, (d, r) in terms.items()),
        "fwd/read": f"{sub.forward_ms / ms:,.0f}×" if sub.forward_ms / ms >= 10 else f"{sub.forward_ms / ms:.1f}×",
        "validate": "refuses" if refused else "accepts"})
    case.figures.update(bytes=size, first_ms=first, read_ms=ms, difference=worst, terms=terms,  # type: ignore[attr-defined]
                        forward_ms=sub.forward_ms, refused=[why for _, why in refused], meta=store.taps)
    return ms, peak, max(worst.values(), default=0.0)


def layout_note(objective: str, layout: str, figures: dict[str, Any]) -> str | None:
    """What a layout row's figures mean where it matters (None: nothing to say): masked and top-k differences,
    taps a layout leaves whole, ``validate``'s refusal."""
    meta, spec, said = figures["meta"], LAYOUTS[layout], []
    masked = [t for t, m in meta.items() if m.get("masked")]
    top = [t for t, m in meta.items() if m.get("topk")]
    said += [f"max |Δ| of {', '.join(masked)} inside the mask only"] if masked else []
    said += [f"max |Δ| of {', '.join(top)}: of the softmax probabilities"] if top else []
    whole = [t for t in meta if ("voxels" in spec and t not in masked) or ("topk" in spec and t not in top)]
    if whole:
        said.append(f"{', '.join(whole)} stored whole: the layout does not apply to "
                    + ("them" if len(whole) > 1 else "it"))
    if "voxels" in spec and not masked:
        said.append("the mask's voxel index is stored besides, read by no tap")
    said += [f"validate refuses it: {why}" for why in figures["refused"]]
    return f"{objective}: " + "; ".join(said) if said else None


def forward_note(objective: str, sub: Subject) -> str:
    """A family's line: its taps, the labels' mask fractions, the store's draws, how the reads are timed."""
    ignore = sub.info.classes.ignore_index
    valid = statistics.mean(float((t != ignore).float().mean()) for t in sub.labels)
    occupied = statistics.mean(float(((t != ignore) & (t != 0)).float().mean()) for t in sub.labels)
    taps = ", ".join(f"{tap} ({kind})" for tap, kind in sub.taps.items())
    draws = (f"a store holds each sample under the {sub.draws} draws of train.augment: {sub.draws}× the bytes a "
             "sample" if sub.draws > 1 else "one draw a sample (no train.augment)")
    return (f"{objective}: the stage reads {taps}; the synthetic labels keep {100 * valid:.1f} % of the voxels as "
            f"valid and {100 * occupied:.1f} % as occupied (mean of {len(sub.labels)} samples); {draws}; forward: "
            f"median of {sub.timed} after a warm-up; reads: one sample a batch, the median of {READS} reads of each "
            f"after the first (1st read ms: opening the shard with its SHA-256 check)")


def unstorable(spec: dict[str, Any]) -> str | None:
    """Why a stage's distillation cannot read a store, from its terms' cards (None: it reads teacher taps and calls
    nothing of the teacher), worded as ``validate`` says it."""
    from distilkit.registry import OBJECTIVES

    why, reads = [], False
    for i, term in enumerate(spec["distill"]):
        card = OBJECTIVES.card(term["name"])
        if card.REQUIRES:
            why.append(f"distill[{i}] ({term['name']}) calls the teacher's {', '.join(sorted(card.REQUIRES))}(): "
                       "it needs the teacher itself, not its stored outputs")
        reads = reads or bool(card.TEACHER_ROLES)
        if not card.TEACHER_ROLES and not card.REQUIRES:
            why.append(f"distill[{i}] ({term['name']}) reads no teacher tap")
    return "; ".join(why) if why or not reads else None


@register("teacher-store")
def teacher_store_cases(device: torch.device, quick: bool, test: bool = False) -> list[Case]:
    """A forward row and a row for each layout of each paper recipe's distillation stage that reads teacher taps
    (built lazily: nothing runs until a row does), a line for each that cannot be stored. ``test``: the tests'
    sizes and the ``size: tiny`` stand-ins (seconds on a CPU)."""
    import yaml

    _FAILED.clear()
    if not PAPER_RECIPES.is_dir():
        return [Case("teacher-store: paper recipes", "every one", lambda: torch.zeros(()), None, [],
                     skipped=f"{PAPER_RECIPES} is not here (the recipes are a checkout's, not the package's)")]
    size = "tiny" if test else "paper"
    cases = []
    for path in sorted(PAPER_RECIPES.glob("*.yaml")):
        recipe = yaml.safe_load(path.read_text())
        for stage, spec in recipe["stages"].items():
            if not spec.get("distill") or "from" not in (spec.get("teacher") or {}):
                continue
            adapter = recipe["stages"][spec["teacher"]["from"]]["model"]["adapter"]
            family = FAMILIES.get(adapter, adapter)
            where = f"{path.stem} {stage}"
            why = unstorable(spec)
            if why is not None:
                cases.append(Case(f"teacher-store: {family}", where, lambda: torch.zeros(()), None, [],
                                  skipped=f"its distillation cannot read a store: {why}"))
                continue
            make = functools.partial(build, path.stem, stage, device, quick, test)
            get = functools.partial(subject, f"{where} {device} {quick} {test}", make)
            forward = f"teacher-store: {family} forward"
            cases.append(row_case(forward, f"{where}; size {size}, batch 1",
                                  lambda case, get=get: forward_figures(get(), case),
                                  lambda case, get=get, o=forward: forward_note(o, get())))
            cases += [row_case(f"teacher-store: {family} {layout}", f"{where}; {SAMPLES} samples",
                               lambda case, get=get, lay=layout: read_row(get(), lay, device, case),
                               lambda case, lay=layout: layout_note(case.objective, lay, case.figures))
                      for layout in LAYOUTS]
    return cases


def row_case(objective: str, size: str, measure: Callable[[Case], tuple[float, int | None, float]],
             note: Callable[[Case], str | None]) -> Case:
    """A row measured by ``measure(case)``, with ``note(case)`` under the table where it says something (asked
    after measuring, as the runner does); ``case.figures``: its raw figures, for the tests."""
    case = Case(objective, size, lambda: torch.zeros(()), None, [])
    case.figures = {}  # type: ignore[attr-defined]

    def run() -> tuple[float, int | None, float]:
        figures = measure(case)
        line = note(case)
        case.note = None if line is None else lambda _: line
        return figures

    case.measure = run
    return case


def forward_figures(sub: Subject, case: Case) -> tuple[float, int | None, float]:
    case.figures.update(forward_ms=sub.forward_ms, timed=sub.timed)  # type: ignore[attr-defined]
    return sub.forward_ms, sub.forward_peak, 0.0


__all__ = ["LAYOUTS", "READS", "REPEAT", "SAMPLES", "Subject", "build", "release",
           "resolved", "row_case", "teacher_store_cases", "write_store"]
