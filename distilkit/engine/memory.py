"""Peak memory of one training step, estimated before training (``distilkit validate``), and the one-line error
when a stage runs out of memory anyway.

The estimate runs the stage's real training step — student, teacher (random weights: the same tensors), every
term, backward and the optimizer's first step — on one sample of a small copy of the data (the dataset's
:class:`~distilkit.data.probe.ProbePlan`), and records the peak of the bytes PyTorch holds (the profiler's
allocation events on the CPU, ``max_memory_allocated`` on CUDA). What does not grow with the batch or the grid —
parameters, their gradients, the optimizer's state — is counted once; the rest is taken per sample, scaled to
the recipe's size and multiplied by ``train.batch_size``; extrapolated sizes get a range (see :func:`estimate_stage`).
It counts PyTorch's tensors, not the Python process around them (about 0.5 GB more).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from distilkit.errors import DistilkitError

GB = 1024**3


class OutOfMemoryError(DistilkitError):
    """A stage needed more memory than the machine (or the GPU) has."""


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

    @property
    def figure(self) -> str:
        if self.high <= 1.1 * self.low:
            return f"about {self.high / GB:.2f} GB"
        return f"{self.low / GB:.1f}-{self.high / GB:.1f} GB"

    def line(self) -> str:
        free = f" of {self.available / GB:.1f} GB free" if self.available is not None else ""
        return (f"stage {self.stage}: {self.figure} per training step on the {self.device} "
                f"(batch {self.batch_size}, {self.size}; {self.how}){free}")

    def warning(self) -> str | None:
        """What to say when the step may not fit in what is free (None: it fits with room to spare)."""
        if self.available is None or self.high <= 0.8 * self.available:
            return None
        free = f"the {self.available / GB:.1f} GB free on the {self.device}"
        if self.low > self.available:
            return f"stage {self.stage} needs at least {self.low / GB:.1f} GB per training step, more than {free}"
        return f"stage {self.stage} may need up to {self.high / GB:.1f} GB per training step, close to or more than {free}"


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


def _tensor_bytes(obj: Any) -> int:
    import torch

    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(_tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(_tensor_bytes(v) for v in obj)
    return 0


def peak_of_step(step: Any, device: Any) -> int:
    """Peak bytes PyTorch allocates while ``step()`` runs, above what was allocated before."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
        base = torch.cuda.memory_allocated(device)
        torch.cuda.reset_peak_memory_stats(device)
        step()
        torch.cuda.synchronize(device)
        return int(torch.cuda.max_memory_allocated(device) - base)
    from torch.profiler import ProfilerActivity, profile

    with _quiet_stderr(), profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        step()
    events = sorted((e.start_ns(), e.nbytes()) for e in prof.profiler.kineto_results.events() if e.name() == "[memory]")
    live = peak = 0
    for _, nbytes in events:
        live += nbytes
        peak = max(peak, live)
    return peak


def measure_step(res: Any, stage_name: str, params: Any) -> tuple[float, float]:
    """One training step of ``stage_name`` at batch size 1 on the first training sample of the data ``params``:
    (bytes that do not grow with the data — parameters, gradients, optimizer state —, peak bytes in all)."""
    from distilkit.engine.probe import probe_trainer

    with tempfile.TemporaryDirectory() as tmp:
        trainer = probe_trainer(res, stage_name, params, Path(tmp))
        batch = trainer.first_batch()
        modules = [trainer.student, trainer.task, trainer.objectives, trainer.connectors,
                   *([trainer.teacher] if trainer.teacher is not None else [])]
        weights = sum(_tensor_bytes(list(m.parameters())) + _tensor_bytes(list(m.buffers())) for m in modules)
        before = weights + _tensor_bytes(batch.inputs) + _tensor_bytes(batch.targets)
        trainer.student.train()
        peak = peak_of_step(lambda: trainer.train_step(batch, 0), trainer.device)
        fixed = weights + _tensor_bytes([p.grad for p in trainer.trainable if p.grad is not None])
        fixed += sum(_tensor_bytes(list(opt.state.values()))
                     for opt in [trainer.optimizer, *[o for o in trainer.own_optimizers if o is not None]])
    return float(fixed), float(before + peak)


def estimate_stage(res: Any, stage_name: str) -> MemoryEstimate | None:
    """The estimate for one stage (None: the stage does not train, or its data has no probe plan)."""
    from distilkit.engine.stage import pick_device
    from distilkit.registry import DATASETS

    stage = res.stages[stage_name]
    train = stage.spec.train
    if train.steps == 0:
        return None
    probe = DATASETS.entry(res.recipe.data.dataset).meta.get("probe")
    if probe is None:
        return None
    plan = probe(res.data_params)
    measured = [(size, *measure_step(res, stage_name, params)) for params, size in plan.probes]
    fixed = measured[-1][1]
    per_sample = [(size, total - fixed) for size, _, total in measured]
    (s1, v1), (s2, v2) = per_sample[0], per_sample[-1]
    # The peak is that of the phase that dominates (e.g. a point branch at small grids, the voxels at large ones),
    # so between two probes the line through them bounds it from below and scaling the larger probe in proportion
    # to the size from above (measured here: 0.70 and 1.41 x the full-grid peak for a point-heavy SCPNet, 1.03 and
    # 1.09 x for a light one).
    high = v2 * plan.target / s2
    low = v2 + (v2 - v1) / (s2 - s1) * (plan.target - s2) if s2 != s1 else high
    if plan.target == s2:
        how = "measured"
    elif s1 == s2:
        how = f"measured at {s2:,.0f} {plan.unit}, scaled"
    else:
        how = f"extrapolated from {s1:,.0f} and {s2:,.0f} {plan.unit}"
    device = str(pick_device(train.device))
    b = train.batch_size
    return MemoryEstimate(stage_name, fixed + b * max(min(low, high), 0.0), fixed + b * max(high, low, 0.0), b,
                          plan.describe, how, device, available_memory(device))


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether an exception is an allocation failure (CPU allocator, CUDA, or Python's MemoryError)."""
    if isinstance(exc, MemoryError):
        return True
    import torch

    if isinstance(exc, torch.OutOfMemoryError):
        return True
    text = str(exc)
    return isinstance(exc, RuntimeError) and ("can't allocate memory" in text or "out of memory" in text.lower()
                                              or "Cannot allocate memory" in text)


def _cause(exc: BaseException) -> str:
    """The failed allocation in a few words (the allocator's message is long)."""
    import re

    text = str(exc)
    cpu = re.search(r"tried to allocate (\d+) bytes", text)
    if cpu:
        return f"an allocation of {int(cpu.group(1)) / 2**20:,.0f} MiB failed"
    gpu = re.search(r"Tried to allocate ([\d.]+ [KMG]iB)", text)
    if gpu:
        return f"an allocation of {gpu.group(1)} on the GPU failed"
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return first if len(first) <= 120 else first[:117].rsplit(" ", 1)[0] + "..."


def out_of_memory(stage: Any, info: Any, exc: BaseException, kept: str) -> OutOfMemoryError:
    """The one-line error for a stage that ran out of memory: where, at what size, and what to lower."""
    grid = f"a {'x'.join(map(str, info.grid.shape))} grid" if getattr(info, "grid", None) is not None else "its data"
    return OutOfMemoryError(
        f"stage {stage.name!r} ran out of memory ({_cause(exc)}; train.batch_size {stage.spec.train.batch_size}, "
        f"{grid}, adapter {stage.student.adapter}); {kept}. Lower train.batch_size, the grid (data.params.scale) or "
        "the model's size; `distilkit validate` estimates the memory a training step needs.")


__all__ = ["MemoryEstimate", "OutOfMemoryError", "available_memory", "estimate_stage", "is_out_of_memory",
           "measure_step", "out_of_memory"]
