"""How ``distilkit bench step`` measures one step the way a GPU user judges it (:func:`measure_step`): the median of
:data:`TIMED` timed steps after a warm-up (CUDA events on CUDA, ``perf_counter`` elsewhere), the peak memory allocated
and reserved (CUDA's allocator counters; on the CPU the bytes live before the step plus the profiler's peak during
it, nothing reserved), the host syncs of one step (:mod:`distilkit.bench.syncs`) and one profiled step — on CUDA the
GPU-busy time (the union of its kernels', copies' and fills' spans) and the top kernels by time, on the CPU the top
ops by self CPU time. Not a benchmark: no case is registered here."""

from __future__ import annotations

import gc
import statistics
import time
from typing import Any, Callable

import torch
from torch import Tensor

from distilkit.bench.base import Skipped, time_left
from distilkit.bench.syncs import host_syncs

TIMED = 5  # timed steps per row, after a warm-up step and the step that measures memory
TOP = 5  # ops (CPU) or kernels (CUDA) named per row
GPU_WORK = ("kernel", "gpu_memcpy", "gpu_memset")  # the profiler's activities that occupy the GPU (Kineto's names)


def busy_ms(intervals: list[tuple[float, float]]) -> float:
    """Milliseconds covered by the union of ``(start, end)`` intervals in microseconds (kernels on several streams
    that overlap count once)."""
    total, reach = 0.0, float("-inf")
    for start, end in sorted(intervals):
        if end > reach:
            total += end - max(start, reach)
            reach = end
    return total / 1000


def top_by_time(items: list[tuple[str, float, int]], n: int = TOP) -> list[tuple[str, float, int, float]]:
    """The ``n`` names with the most time over ``(name, microseconds, calls)`` items (a name may come many times):
    (name, milliseconds, calls, share of all the items' time), the longest first."""
    by: dict[str, list[float]] = {}
    for name, us, calls in items:
        total_us, count = by.setdefault(name, [0.0, 0])
        by[name] = [total_us + us, count + calls]
    total = sum(v[0] for v in by.values()) or 1.0
    ranked = sorted(by.items(), key=lambda kv: -kv[1][0])[:n]
    return [(name, us / 1000, int(calls), us / total) for name, (us, calls) in ranked]


def _timed_ms(step: Callable[[], Any], device: torch.device) -> float:
    """One step's milliseconds: CUDA events around it on CUDA (the stream's time from the step's first launch to the
    end of its last kernel), ``perf_counter`` elsewhere."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        step()
        end.record()
        end.synchronize()
        return float(start.elapsed_time(end))
    t0 = time.perf_counter()
    step()
    return (time.perf_counter() - t0) * 1000


def _peak(step: Callable[[], Any], device: torch.device, held: Callable[[], int]) -> tuple[int, int | None]:
    """(peak bytes allocated, reserved) during one step: CUDA's allocator counters (the whole process's on the
    device, the cache emptied first so that reserved is this step's), or on the CPU what was live before the step
    plus the profiler's peak during it (nothing is reserved)."""
    if device.type == "cuda":
        gc.collect()
        torch.cuda.synchronize(device)
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
        step()
        torch.cuda.synchronize(device)
        return int(torch.cuda.max_memory_allocated(device)), int(torch.cuda.max_memory_reserved(device))
    from distilkit.engine.memory.estimate import peak_of_step

    before = held()
    return before + peak_of_step(step, device), None


def _profile(step: Callable[[], Any], device: torch.device) -> tuple[list[tuple[str, float, int, float]], float | None]:
    """One profiled step: (its top kernels by time and the milliseconds the GPU was busy, on CUDA; its top ops by
    self CPU time and None elsewhere)."""
    from torch.profiler import ProfilerActivity, profile

    from distilkit.engine.memory.estimate import _quiet_stderr

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with _quiet_stderr(), profile(activities=activities) as prof:
        step()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
    if device.type == "cuda":  # the GPU's own work: kernels, copies, fills (not the annotations of CPU ranges)
        gpu = [e for e in prof.profiler.kineto_results.events() if e.device_type() == torch.autograd.DeviceType.CUDA
               and e.activity_type() in GPU_WORK and not e.is_user_annotation()]
        spans = [(e.start_ns() / 1000, e.end_ns() / 1000) for e in gpu]
        return top_by_time([(e.name(), (e.end_ns() - e.start_ns()) / 1000, 1) for e in gpu]), busy_ms(spans)
    ops = [e for e in prof.key_averages() if not e.key.startswith("[")]  # "[memory]" and the like are not ops
    return top_by_time([(e.key, float(e.self_cpu_time_total), int(e.count)) for e in ops]), None


def _on_time(what: str) -> None:
    if time_left() <= 0:
        raise Skipped(f"the time limit ran out during it ({what})")


def measure_step(step: Callable[[], Any], device: torch.device, held: Callable[[], int]) -> dict[str, Any]:
    """The figures of one row from ``step()`` (one whole step; it returns the loss or None): a warm-up step, one
    that measures memory, :data:`TIMED` timed steps, one whose host syncs are counted, one profiled."""
    _on_time("before its warm-up step")  # building it (data, models) may have taken the rest
    value = step()
    _on_time("after its warm-up step")
    peak, reserved = _peak(step, device, held)
    times = []
    for i in range(TIMED):
        _on_time(f"after {i} of its {TIMED} timed steps")
        times.append(_timed_ms(step, device))
    _on_time("before the step whose syncs it counts")
    with host_syncs(device) as syncs:
        step()
    _on_time("before its profiled step")
    top, busy = _profile(step, device)
    ms = statistics.median(times)
    return {"ms": ms, "times": times, "peak": peak, "reserved": reserved, "syncs": len(syncs), "sync_ops": syncs,
            "top": top, "busy": None if busy is None else busy / ms,
            "value": float(value.detach()) if isinstance(value, Tensor) else float(value or 0.0)}


def held_bytes(modules: list[Any], optimizers: list[Any], batch: Any) -> int:
    """Bytes live between steps: the modules' parameters, buffers and gradients, the optimizers' state, the batch's
    input and target tensors (the CPU peak's base)."""
    from distilkit.engine.memory.estimate import tensor_bytes

    params = {id(p): p for m in modules if m is not None for p in m.parameters()}
    buffers = [b for m in modules if m is not None for b in m.buffers()]
    grads = [p.grad for p in params.values() if p.grad is not None]
    state = [list(opt.state.values()) for opt in optimizers if opt is not None]
    data = [getattr(batch, "inputs", None), getattr(batch, "targets", None)]
    return tensor_bytes([*params.values(), *buffers, *grads, *state, *[d for d in data if isinstance(d, dict)]])


__all__ = ["GPU_WORK", "TIMED", "TOP", "busy_ms", "held_bytes", "measure_step", "top_by_time"]
