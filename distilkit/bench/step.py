"""``distilkit bench step``: one training step measured the way a GPU user judges it, for each paper network
(``size: paper``) as a **student** (train mode: forward, backward and an Adam step) and as a **teacher** (eval mode,
the forward under ``torch.no_grad()``), and for the distillation stage of each shipped paper recipe
(``recipes/paper/*.yaml``: its student, teacher, objectives and task losses, resident together, one step of the
stage's own trainer — :func:`distilkit.engine.memory.probe.probe_trainer`, as ``validate`` and its memory estimate
build it — teacher with random weights), each in fp32, bf16 (autocast) and fp16 (autocast and a
``torch.amp.GradScaler``) on every sparse backend present (:mod:`distilkit.sparse.backend`).

Each row (:func:`distilkit.bench.measure.measure_step`): the median of 5 timed steps after a warm-up step and one
that measures memory (CUDA events on CUDA, ``perf_counter`` on the CPU); the peak memory allocated and reserved
(``torch.cuda.max_memory_allocated`` / ``max_memory_reserved`` on CUDA; on the CPU the bytes live before the step —
parameters, buffers, gradients, the optimizers' state, the batch — plus the profiler's peak during it,
``peak_of_step``; reserved "n/a"); the host syncs of one step (:mod:`distilkit.bench.syncs`: CUDA's sync debug mode,
the ops that would sync on the CPU); and one profiled step (``torch.profiler``): on CUDA the GPU-busy fraction — the
union of its kernels', copies' and fills' time over the median step — and the top kernels by time, on the CPU the
top ops by self CPU time (the notes). With fp16, the scaler's scale after the steps.

Inputs are the papers' (:func:`distilkit.bench.fixtures.data_sizes`: a 64-beam scan of the synthetic streets on the
256 x 256 x 32 grid, a 370 x 1220 image, an 18,000-point scan completed to 180,000 points) at the recipes' batch
sizes (a network's: the paper recipe's stage that trains it; as a teacher, the stage it teaches), one sample
repeated to the batch; ``--quick`` a quarter of each, and ``test=True`` (tests only) the tests' sizes. The recipes'
SemanticKITTI folders are replaced by the synthetic streets at the same sizes (their data, with the recipe's scans,
images and frames; no folder is read). LiDiff as a teacher runs one sampler step (one network evaluation, the
denoising pass ScoreLiDAR's terms ask of it; its 50-step completion is 50 of them), its refiner refines the ground
truth's scene. Combinations that cannot run are lines under the table with the reason: a precision torch refuses
on the device, a backend that is missing or refuses the call (its dtype, autocast's dtype, gradients with spconv's
CPU build), a network without sparse convolutions on a library backend, running out of the device's memory, the
time limit (``--time-limit``).

One subject (a network with its optimizer, or a recipe's trainer) is resident at a time: it is built when its first
row runs and released before the next is built, so each row's peak is its own.
"""

from __future__ import annotations

import dataclasses
import functools
import gc
import traceback
from typing import Any, Callable

import torch
from torch import Tensor

from distilkit.bench.base import Case, Skipped, register, scratch_dir
from distilkit.bench.fixtures import (PAPER_RECIPES, NetworkCase, build, data_sizes, network_cases, paper_recipe,
                                      tap_loss)
from distilkit.bench.measure import held_bytes, measure_step
from distilkit.engine.train.precision import AUTOCAST, autocast

PRECISIONS = ("fp32", "bf16", "fp16")
LIBRARIES = ("spconv", "spconv-triton")
# family -> (paper recipe, the stage that trains the network: its batch as a student; the stage it teaches, if any)
STAGES = {"SCPNet": ("scpnet", "student", "student_dskd"), "JS3C-Net": ("js3cnet", "student", "student_dskd"),
          "LiDiff": ("scorelidar", "teacher", "student"), "LiDiff refine": ("scorelidar", "refiner", None),
          "VoxFormer": ("scribble2scene", "student", "student"),
          "Dean-Labeler": ("scribble2scene", "dean", None)}
TEACHER_PARAMS = {"LiDiff": {"sample_steps": 1}}  # its eval forward: one sampler step, one network evaluation


# ----------------------------------------------------------------------------------------------------- the subjects


@dataclasses.dataclass
class Subject:
    """What a row's step runs on, once built: the step (per precision), the bytes live between steps, whether it
    holds a sparse convolution, and the GradScaler of its fp16 step (None: none)."""

    step: Callable[[], Any]
    held: Callable[[], int]
    sparse: bool
    scaler: Any = None


_RESIDENT: dict[str, Any] = {}  # the one subject built (by key), released before another is built


def resident(key: str, make: Callable[[], Any]) -> Any:
    """The object built by ``make`` under ``key``: the resident one if it is ``key``'s, else — the resident one
    released first — a new one."""
    if key not in _RESIDENT:
        release()
        _RESIDENT[key] = make()
    return _RESIDENT[key]


def release() -> None:
    """Release the resident subject (and, on CUDA, the allocator's cache)."""
    _RESIDENT.clear()
    gc.collect()
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.empty_cache()


def precision_problem(device: torch.device, precision: str) -> str | None:
    """Why ``precision`` cannot run on ``device`` here (None: it can): torch's autocast refusing the dtype there,
    a GPU without bfloat16, a GradScaler that cannot scale there."""
    import warnings

    if precision == "fp32":
        return None
    if device.type == "cuda" and precision == "bf16" and not torch.cuda.is_bf16_supported():
        return f"this GPU ({torch.cuda.get_device_name(device)}) has no bfloat16"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with autocast(device, precision):
                on = torch.is_autocast_enabled(device.type)
            scaler = torch.amp.GradScaler(device.type) if precision == "fp16" else None
        except Exception as exc:  # a torch without autocast or a GradScaler for this device type
            return f"torch {torch.__version__} refuses it on the {device.type}: {type(exc).__name__}: {exc}"
    said = " ".join(str(w.message).splitlines()[0] for w in caught)
    why = f": {said}" if said else ""
    if not on:
        return f"torch {torch.__version__} disables {precision} autocast on the {device.type}{why}"
    if scaler is not None and not scaler.is_enabled():
        return f"torch {torch.__version__}'s GradScaler is disabled on the {device.type}{why}"
    return None


def network_subject(case: NetworkCase, role: str, batch_size: int, device: torch.device, precision: str) -> Subject:
    """The network of ``case`` as a student (train mode, Adam, the precision's GradScaler) or a teacher (eval mode,
    no gradient): its built model (resident across the precisions of the role) and the precision's step."""
    from distilkit.sparse import uses_sparse

    def make() -> Any:
        model, batch = build(case, device, batch_size)
        if role == "teacher" and case.adapter == "lidiff-refine":  # it refines a completion: the scene's size
            from distilkit.structures import PointCloud

            batch.inputs["coarse"] = PointCloud(batch.field("scene"), batch.field("scene_lengths"))
        optimizer = torch.optim.Adam(model.parameters(), lr=1e-4) if role == "student" else None
        return model.train(role == "student"), batch, optimizer

    model, batch, optimizer = resident(f"network {case.family} {role}", make)
    held = lambda: held_bytes([model], [optimizer], batch)  # noqa: E731
    if role == "teacher":
        def look() -> None:
            with torch.no_grad(), autocast(device, precision):
                model(batch)
        return Subject(look, held, uses_sparse(model))
    scaler = torch.amp.GradScaler(device.type, enabled=precision == "fp16")

    def learn() -> Tensor:
        optimizer.zero_grad(set_to_none=True)
        with autocast(device, precision):
            out = model(batch)
        loss = tap_loss(out)
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
        return loss.detach()
    return Subject(learn, held, uses_sparse(model), scaler if scaler.is_enabled() else None)


def load(name: str) -> dict[str, Any]:
    """Paper recipe ``name`` as its YAML reads."""
    import yaml

    return yaml.safe_load((PAPER_RECIPES / f"{name}.yaml").read_text())


@functools.cache
def recipe_batch(name: str, stage: str) -> int:
    """The batch size of stage ``stage`` of paper recipe ``name`` (read once: every row of a network asks)."""
    return int(((load(name)["stages"][stage].get("train") or {}).get("batch_size")) or 1)


def resolved(name: str, stage: str, device: torch.device, quick: bool, test: bool, precision: str) -> Any:
    """Paper recipe ``name`` resolved at the bench's data, its stage ``stage`` on ``device`` in ``precision``."""
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.recipe import recipe_from_dict

    recipe = paper_recipe(name, quick, test, device.type)
    recipe["stages"][stage]["train"]["precision"] = precision
    path = str(PAPER_RECIPES / f"{name}.yaml")
    return resolve(recipe_from_dict(recipe, path), path)


def recipe_subject(name: str, stage: str, device: torch.device, quick: bool, test: bool, precision: str) -> Subject:
    """Stage ``stage`` of paper recipe ``name`` as its trainer runs it (student, teacher, terms, the optimizers;
    the GradScaler the trainer makes for fp16), at the recipe's batch size."""
    from distilkit.engine.memory.probe import probe_trainer
    from distilkit.sparse import uses_sparse

    def make() -> Any:
        res = resolved(name, stage, device, quick, test, precision)
        size = res.stages[stage].spec.train.batch_size
        trainer = probe_trainer(res, stage, res.data_params, scratch_dir("step-"), batch_size=size)
        batch = trainer.prepare(trainer.collate([trainer.train_set[0]] * size))  # the batch from one scene
        trainer.student.train()
        return trainer, batch, [0]

    trainer, batch, count = resident(f"recipe {name} {stage} {precision}", make)

    def learn() -> float:
        count[0] += 1
        return trainer.train_step(batch, count[0])["loss"]

    def held() -> int:
        modules = [trainer.student, trainer.task, trainer.objectives, trainer.connectors, trainer.teacher]
        return held_bytes(modules, [trainer.optimizer, *trainer.own_optimizers], batch)

    sparse = uses_sparse(trainer.student) or (trainer.teacher is not None and uses_sparse(trainer.teacher))
    return Subject(learn, held, sparse, trainer.scaler if trainer.scaler.is_enabled() else None)


# ------------------------------------------------------------------------------------------------------ the rows


def _short(name: str, width: int = 60) -> str:
    """A kernel's or op's name cut to ``width`` characters (CUDA kernels' template names run to hundreds)."""
    return name if len(name) <= width else name[:width - 1] + "…"


def row(objective: str, size: str, device: torch.device, backend: str, subject: Callable[[], Subject]) -> Case:
    """One row: ``subject()`` built (or the resident one) and measured with its sparse convolutions on ``backend``;
    its figures in the row's columns and its profile in a note."""
    from distilkit.engine.train.oom import is_out_of_memory
    from distilkit.sparse import backend as backends

    figures: dict[str, Any] = {}
    case = Case(objective, size, lambda: torch.zeros(()), None, [])

    def measure() -> tuple[float, int | None, float]:
        try:
            built = subject()
            if backend != "torch" and not built.sparse:
                raise Skipped(f"it holds no sparse convolution (every backend computes its step alike: the torch "
                              f"row's)")
            with backends.using(backend):
                figures.update(measure_step(built.step, device, built.held))
        except backends.SparseBackendError as exc:
            raise Skipped(str(exc)) from None
        except Skipped:
            raise
        except Exception as exc:  # a row that fails leaves the others to run (its traceback on stderr)
            release()
            if is_out_of_memory(exc):
                raise Skipped(f"out of the {device.type}'s memory ({str(exc).splitlines()[0][:200]})") from None
            traceback.print_exc()
            raise Skipped(f"it failed — {type(exc).__name__}: {str(exc)[:300]}") from None
        figures["scaler"] = built.scaler
        figures["scale"] = built.scaler.get_scale() if built.scaler is not None else None
        case.columns.update({
            "reserved": "n/a" if figures["reserved"] is None else f"{figures['reserved'] / 2**20:,.0f} MiB",
            "syncs": str(figures["syncs"]),
            "GPU busy": "n/a" if figures["busy"] is None else f"{100 * figures['busy']:.0f} %",
            "fp16 scale": "—" if figures["scale"] is None else f"{figures['scale']:,.0f}"})
        return figures["ms"], figures["peak"], figures["value"]

    def note(_: dict[str, Any]) -> str:
        ranked = ", ".join(f"{_short(name)} {100 * share:.0f} % ({ms:,.1f} ms, {n}x)"
                           for name, ms, n, share in figures["top"])
        if figures["busy"] is not None:
            return (f"{objective}, {size}: GPU busy {100 * figures['busy']:.0f} % of the {figures['ms']:,.1f} ms "
                    f"step; top kernels by time: {ranked}")
        return f"{objective}, {size}: top ops by self CPU time: {ranked}"

    case.measure, case.note = measure, note
    case.figures = figures  # type: ignore[attr-defined]  # the tests read the raw figures
    return case


def backends_here(device: torch.device,
                  precisions: list[str]) -> tuple[list[str], list[Case], set[tuple[str, str, bool]]]:
    """(the sparse backends present on ``device`` — torch always —; a line for each library that is missing or
    refuses a kind of step here, with its reason; the (backend, precision, gradients) it refuses)."""
    from distilkit.sparse import backend

    present, lines, refused = ["torch"], [], set()
    for name in LIBRARIES:
        why = backend.problem(name, device.type)
        if why is not None:
            lines.append(Case(f"step: {name} backend", f"every step on the {device.type}", lambda: torch.zeros(()),
                              None, [], skipped=why))
            continue
        present.append(name)
        for precision in precisions:
            for gradients, steps in ((True, "students' and recipes' steps"), (False, "teachers' forwards")):
                call = backend.Call(device.type, AUTOCAST.get(precision, torch.float32), precision != "fp32",
                                    gradients)
                why = backend.refusal(name, call)
                if why is not None:
                    refused.add((name, precision, gradients))
                    lines.append(Case(f"step: {name} backend", f"{precision} {steps}", lambda: torch.zeros(()),
                                      None, [], skipped=why))
    return present, lines, refused


@register("step")
def step_cases(device: torch.device, quick: bool, test: bool = False) -> list[Case]:
    """The rows (built lazily: nothing is built until a row runs), with a line for each combination that cannot run
    here. ``test``: the tests' sizes (seconds on a CPU)."""
    cases: list[Case] = []
    precisions = []
    for precision in PRECISIONS:
        why = precision_problem(device, precision)
        if why is None:
            precisions.append(precision)
        else:
            cases.append(Case(f"step: {precision}", f"every step on the {device.type}", lambda: torch.zeros(()),
                              None, [], skipped=why))
    backends, lines, refused = backends_here(device, precisions)
    combos = [(p, b) for p in precisions for b in backends]
    cases += lines
    if not PAPER_RECIPES.is_dir():
        cases.append(Case("step: paper recipes", "every one", lambda: torch.zeros(()), None, [],
                          skipped=f"{PAPER_RECIPES} is not here (the recipes are a checkout's, not the package's); the "
                                  f"networks run at batch 1"))
    cases += network_rows(device, quick, test, [c for c in combos if (c[1], c[0], True) not in refused],
                          [c for c in combos if (c[1], c[0], False) not in refused])
    if PAPER_RECIPES.is_dir():
        cases += recipe_rows(device, quick, test, [c for c in combos if (c[1], c[0], True) not in refused])
    return cases


def network_rows(device: torch.device, quick: bool, test: bool, learning: list[tuple[str, str]],
                 looking: list[tuple[str, str]]) -> list[Case]:
    """Each paper network as a student in the (precision, backend) pairs ``learning`` and as a teacher in
    ``looking``, at the batch of the recipe stage that trains it, or that it teaches."""
    cases = []
    for case in network_cases(quick, test, sizes=("paper",)):
        recipe, trains, teaches = STAGES[case.family]
        for role, combos in (("student", learning), ("teacher", looking)):
            stage = teaches if role == "teacher" and teaches is not None else trains
            batch = recipe_batch(recipe, stage) if PAPER_RECIPES.is_dir() else 1
            subject_case = case if role == "student" else dataclasses.replace(
                case, params={**case.params, **TEACHER_PARAMS.get(case.family, {})})
            what = case.what + ("; one sampler step" if role == "teacher" and case.family in TEACHER_PARAMS else "")
            cases += [row(f"step: {case.family} {role}", f"{precision}, {name}; batch {batch}, {what}", device, name,
                          lambda c=subject_case, r=role, b=batch, p=precision: network_subject(c, r, b, device, p))
                      for precision, name in combos]
    return cases


def recipe_rows(device: torch.device, quick: bool, test: bool, combos: list[tuple[str, str]]) -> list[Case]:
    """The distillation stage (one with ``distill``) of each paper recipe in the (precision, backend) pairs
    ``combos``, at its batch size."""
    cases = []
    sizes = data_sizes(quick, test)
    for path in sorted(PAPER_RECIPES.glob("*.yaml")):
        recipe = paper_recipe(path.stem, quick, test)
        data = recipe["data"]["params"]
        if "scan_points" in data:
            what = f"{data['scan_points']:,} -> {data['scene_points']:,} points"
        else:
            grid = "x".join(str(n // sizes["lidar"]["scale"]) for n in (256, 256, 32))
            camera = data.get("camera")
            scans = f"{data['input_frames']} fused {data['beams']}-beam scans" if data["input_frames"] > 1 else \
                f"a {data['beams']}-beam scan"
            what = f"{scans}, {grid}" + (f", {1 + len(camera['previous'])} {camera['height']}x{camera['width']} "
                                         f"images" if camera else "")
        for stage, spec in recipe["stages"].items():
            if not spec.get("distill"):
                continue
            batch = recipe_batch(path.stem, stage)
            tasks = [t["name"] for t in spec["task_losses"]] if "task_losses" in spec else ["the adapter's task loss"]
            terms = " + ".join([t["name"] for t in spec["distill"]] + tasks)
            cases += [row(f"step: recipe {path.stem} {stage}", f"{precision}, {name}; batch {batch}, {what}; {terms}",
                          device, name, lambda n=path.stem, s=stage, p=precision: recipe_subject(n, s, device, quick,
                                                                                                 test, p))
                      for precision, name in combos]
    return cases


__all__ = ["PRECISIONS", "STAGES", "Subject", "backends_here", "network_rows", "network_subject", "precision_problem",
           "recipe_rows", "recipe_subject", "release", "row", "step_cases"]
