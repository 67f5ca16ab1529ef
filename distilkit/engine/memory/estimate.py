"""Peak memory of one training step, estimated before training (``distilkit validate``); the one-line error when a
stage runs out of memory anyway is :mod:`distilkit.engine.train.oom`'s.

The estimate runs the stage's real training step twice — student, teacher (random weights: the same tensors),
every term, backward and the optimizer's step; the second as every later step is, with the optimizer's state — on
one sample of a small copy of the data (the dataset's :class:`~distilkit.data.probe.ProbePlan`), and records the
peak of the bytes PyTorch holds (the profiler's allocation events on the CPU, the allocator's counters on CUDA), in
two phases: the model's (forward, losses, backward) and the optimizer's step. What does not grow with the batch —
parameters, the optimizer's state and its step's temporaries — is counted once; the rest is taken per sample, scaled
to the recipe's size and multiplied by ``train.batch_size``; extrapolated sizes get a range (see
:func:`estimate_stage`).
It counts PyTorch's tensors, not the Python process around them (about 0.5 GiB more).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator


GIB = 1024**3


@dataclass
class MemoryEstimate:
    """Bytes of one training step at the recipe's batch size and size: ``low`` and ``high`` bound it where the
    size was extrapolated (equal where it was measured)."""

    stage: str
    low: float
    high: float
    batch_size: int
    size: str  # the recipe's size in words ("a 256x256x32 grid")
    how: str  # "measured" / "extrapolated from ..."
    device: str
    available: int | None  # bytes free on that device now (None: unknown)
    store: tuple[float, float] | None = None  # a stored stage's teacher store on disk, bounded as the step is

    @property
    def figure(self) -> str:
        if self.high <= 1.1 * self.low:
            return f"about {self.high / GIB:.2f} GiB"
        return f"{self.low / GIB:.1f}-{self.high / GIB:.1f} GiB"

    def line(self) -> str:
        free = f" of {self.available / GIB:.1f} GiB free" if self.available is not None else ""
        line = (f"stage {self.stage}: {self.figure} per training step on the {self.device} "
                f"(batch {self.batch_size}, {self.size}; {self.how}){free}")
        if self.store is not None:
            low, high = self.store
            unit, scale = ("GiB", GIB) if high >= GIB else ("MiB", 2 ** 20)
            disk = f"about {high / scale:.1f} {unit}" if high <= 1.1 * low else \
                f"{low / scale:.1f}-{high / scale:.1f} {unit}"
            line += f"; without its teacher, whose outputs it reads from a store of {disk} on disk"
        return line

    def warning(self) -> str | None:
        """What to say when the step may not fit in what is free (None: it fits with room to spare)."""
        if self.available is None or self.high <= 0.8 * self.available:
            return None
        free = f"the {self.available / GIB:.1f} GiB free on the {self.device}"
        if self.low > self.available:
            return f"stage {self.stage} needs at least {self.low / GIB:.1f} GiB per training step, more than {free}"
        return f"stage {self.stage} may need up to {self.high / GIB:.1f} GiB per training step, close to or more than {free}"


def available_memory(device: str) -> int | None:
    """Bytes that can be allocated now: the GPU's free memory, or the machine's ``MemAvailable`` (Linux)."""
    if device.startswith("cuda"):
        import torch

        return int(torch.cuda.mem_get_info(torch.device(device))[0])
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence what C++ libraries write to the process's stderr (the profiler's start/stop lines)."""
    import sys

    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def tensor_bytes(obj: Any) -> int:
    import torch

    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(tensor_bytes(v) for v in obj)
    return 0


@dataclass(frozen=True)
class StepPeaks:
    """Peak bytes allocated during one step above what was live before it, by phase: ``model`` outside the
    optimizers' steps (forward, losses, backward, the objectives' own updates), and for each optimizer step
    (``Optimizer.step``, in order) the bytes live as it began and its peak."""

    model: int
    optimizer: list[tuple[int, int]]

    @property
    def peak(self) -> int:
        return max([self.model, *(peak for _, peak in self.optimizer)])


def _cuda_peaks(step: Any, device: Any) -> StepPeaks:
    import torch
    from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook

    torch.cuda.synchronize(device)
    base = torch.cuda.memory_allocated(device)
    model, held = 0, 0
    windows: list[tuple[int, int]] = []

    def since_reset() -> int:
        torch.cuda.synchronize(device)
        return int(torch.cuda.max_memory_allocated(device) - base)

    def pre(*_: Any) -> None:
        nonlocal model, held
        model = max(model, since_reset())
        held = int(torch.cuda.memory_allocated(device) - base)
        torch.cuda.reset_peak_memory_stats(device)

    def post(*_: Any) -> None:
        windows.append((held, since_reset()))
        torch.cuda.reset_peak_memory_stats(device)

    torch.cuda.reset_peak_memory_stats(device)
    hooks = [register_optimizer_step_pre_hook(pre), register_optimizer_step_post_hook(post)]
    try:
        step()
    finally:
        for hook in hooks:
            hook.remove()
    return StepPeaks(max(model, since_reset()), windows)


def step_peaks(step: Any, device: Any) -> StepPeaks:
    """Run ``step()`` and return its peaks by phase (the profiler's allocation events on the CPU, split at the
    ``Optimizer.step`` ranges PyTorch records; the allocator's peak counters and optimizer hooks on CUDA)."""
    if device.type == "cuda":
        return _cuda_peaks(step, device)
    from torch.profiler import ProfilerActivity, profile

    with _quiet_stderr(), profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        step()
    events = list(prof.profiler.kineto_results.events())
    ranges = sorted((e.start_ns(), e.end_ns()) for e in events if e.name().startswith("Optimizer.step#"))
    allocations = sorted((e.start_ns(), e.nbytes()) for e in events if e.name() == "[memory]")
    live = model = 0
    windows: list[list[int]] = []
    i = 0
    for t, nbytes in allocations:
        while i < len(ranges) and t > ranges[i][1]:
            i += 1
        inside = i < len(ranges) and ranges[i][0] <= t
        if inside and len(windows) <= i:
            windows.extend([live, live] for _ in range(i + 1 - len(windows)))
        live += nbytes
        if inside:
            windows[i][1] = max(windows[i][1], live)
        else:
            model = max(model, live)
    return StepPeaks(model, [(held, peak) for held, peak in windows])


def peak_of_step(step: Any, device: Any) -> int:
    """Peak bytes PyTorch allocates while ``step()`` runs, above what was allocated before."""
    return step_peaks(step, device).peak


@dataclass(frozen=True)
class StepMemory:
    """Bytes of one training step as it is after the first (the optimizer's state and the last gradients live):
    ``kept`` — parameters, buffers and optimizer state, which do not grow with the batch —; ``model`` —
    the peak outside the optimizer's step —; ``optimizer`` — what was live as the optimizer's step began — and
    ``temporaries`` — what that step allocates on top (its own, a fixed amount)."""

    kept: float
    model: float
    optimizer: float
    temporaries: float
    stored: float = 0.0  # a stored stage's teacher outputs of the sample, in its store layout (bytes on disk)

    @property
    def total(self) -> float:
        return max(self.model, self.optimizer + self.temporaries)


def measure_step(res: Any, stage_name: str, params: Any) -> StepMemory:
    """Two training steps of ``stage_name`` at batch size 1 on the first training sample of the data ``params``,
    measured by phase: the model's phase is the larger of the two (a first step may do one-off work, e.g. fill a
    cache), the optimizer's is the second's (its state exists from then on). A step that fails as the run's would
    (a term on the shapes its taps have, a model) raises :class:`~distilkit.engine.memory.probe.StepFailure`."""
    from distilkit.engine.memory.probe import StoredOutputs, first_step, name_terms, probe_trainer

    with tempfile.TemporaryDirectory() as tmp:
        with first_step(stage_name):  # the recipe's errors, each one line (the term's, with what it read)
            trainer = probe_trainer(res, stage_name, params, Path(tmp))
            name_terms(trainer)
            batch = trainer.first_batch()
        modules = [trainer.student, trainer.task, trainer.objectives, trainer.connectors,
                   *([trainer.teacher] if trainer.teacher is not None else [])]
        optimizers = [trainer.optimizer, *[o for o in trainer.own_optimizers if o is not None]]

        def held() -> tuple[float, float]:
            """(bytes live between steps, of which kept whatever the data)"""
            weights = sum(tensor_bytes(list(m.parameters())) + tensor_bytes(list(m.buffers())) for m in modules)
            kept = weights + sum(tensor_bytes(list(opt.state.values())) for opt in optimizers)
            grads = tensor_bytes([p.grad for p in trainer.trainable if p.grad is not None])
            return kept + grads + tensor_bytes(batch.inputs) + tensor_bytes(batch.targets), kept

        trainer.student.train()
        model = 0.0
        for i in range(2):
            before, kept = held()
            peaks = step_peaks(lambda: _step(trainer, batch, i, stage_name), trainer.device)
            model = max(model, before + peaks.model)
        held_at, top = max(peaks.optimizer, key=lambda w: w[1], default=(0, 0))
        stored = 0.0
        if isinstance(trainer.store, StoredOutputs):
            from distilkit.engine.train.teacher_store import stored_bytes

            stored = float(stored_bytes(trainer.stage, trainer.store.outputs, batch, trainer.info))
    return StepMemory(kept, model, before + held_at, float(top - held_at), stored)


def _step(trainer: Any, batch: Any, step: int, stage_name: str) -> None:
    """One training step of a probe's trainer; what fails in it, the recipe's error (a :class:`StepFailure`)."""
    from distilkit.engine.memory.probe import first_step

    with first_step(stage_name):
        trainer.train_step(batch, step)


def _bounds(points: list[tuple[float, float]], target: float, peak: bool = True) -> tuple[float, float]:
    """Bounds at ``target`` of a per-sample cost measured at (size, bytes) ``points``, taking it to be a sum of
    parts that grow as size^p with 0 <= p <= 1 (a dense grid: p = 1; active voxels of a surface: about 2/3; the
    scan's points: 0), or with ``peak`` the largest of several such sums (the peak of a step that passes through
    phases). Either's growth rate only rises with the size, so continuing the rate between the two probes bounds it
    from below. From above: a sum by the line through the probes (all of the growth in a p = 1 part); a peak by
    growing in proportion to the size (a phase below the others at both probes may overtake them)."""
    import math

    (s1, v1), (s2, v2) = points[0], points[-1]
    v1, v2 = max(v1, 0.0), max(v2, 0.0)
    if s1 == s2 or target == s2:
        return (v2 * target / s2,) * 2
    high = v2 * target / s2 if peak else max(v2, v2 + (v2 - v1) / (s2 - s1) * (target - s2))
    if v1 <= 0 or v2 <= 0:
        return high, high
    rate = min(max(math.log(v2 / v1) / math.log(s2 / s1), 0.0), 1.0)
    return v2 * (target / s2) ** rate, high


def estimate_stage(res: Any, stage_name: str) -> MemoryEstimate | None:
    """The estimate for one stage (None: the stage does not train, or its data has no probe plan); a
    :class:`~distilkit.engine.memory.probe.StepFailure` where its first step fails as the run's would.

    Each probe's step is split in two phases — the model's (forward and backward) and the optimizer's step — whose
    peaks grow differently: the model's with the data; the optimizer's is what the model phase leaves live plus its
    own temporaries, a fixed amount (for Adam a few copies of the parameters: at small probe sizes it is the step's
    peak, and scaling it with the grid would overstate a large grid). Each phase's per-sample part is bounded at
    the recipe's size by :func:`_bounds`, times ``train.batch_size``, plus what is kept whatever the batch (the
    parameters and the optimizer's state; bounded the same way, as a model's parameters may grow with the grid)."""
    from distilkit.engine.assemble.devices import pick_device
    from distilkit.registry import DATASETS

    stage = res.stages[stage_name]
    train = stage.spec.train
    if train.steps == 0:
        return None
    probe = DATASETS.entry(res.recipe.data.dataset).meta.get("probe")
    if probe is None:
        return None
    plan = probe(res.data_params)
    measured = [(size, measure_step(res, stage_name, params)) for params, size in plan.probes]
    b = train.batch_size

    def bound(part: Any, peak: bool = True) -> tuple[float, float]:
        return _bounds([(size, part(m)) for size, m in measured], plan.target, peak)

    kept = bound(lambda m: m.kept, peak=False)  # grows with the grid where parameters do (VoxFormer's queries)
    temporaries = bound(lambda m: m.temporaries, peak=False)
    model = bound(lambda m: m.model - m.kept)
    held = bound(lambda m: m.optimizer - m.kept)
    low, high = (kept[j] + max(b * model[j], b * held[j] + temporaries[j]) for j in (0, 1))
    (s1, _), (s2, _) = measured[0], measured[-1]
    if plan.target == s2:
        how = "measured"
    elif s1 == s2:
        how = f"measured at {s2:,.0f} {plan.unit}, scaled"
    else:
        how = f"extrapolated from {s1:,.0f} and {s2:,.0f} {plan.unit}"
    device = str(pick_device(train.device))
    disk = None
    if measured[-1][1].stored:  # a stored stage: its store on disk, per sample scaled as the step's memory is
        samples = _store_samples(res, stage_name)
        disk = tuple(samples * v for v in bound(lambda m: m.stored, peak=False))
    return MemoryEstimate(stage_name, low, high, b, plan.describe, how, device, available_memory(device), disk)


def _store_samples(res: Any, stage_name: str) -> int:
    """Training samples x augmentation draws: the rows a stage's teacher store holds."""
    from distilkit.data.augment import Augmentation
    from distilkit.registry import DATASETS

    spec = res.stages[stage_name].spec
    entry = DATASETS.entry(res.recipe.data.dataset)
    n = len(entry.obj(res.data_params, "train", None))
    info = entry.meta["info"](res.data_params)
    return n * (Augmentation(spec.train.augment, info.grid).draws if spec.train.augment is not None else 1)


__all__ = ["MemoryEstimate", "StepMemory", "StepPeaks", "available_memory", "estimate_stage", "measure_step",
           "peak_of_step", "step_peaks", "tensor_bytes"]
