"""The CPUs this process may use (its affinity mask, not the machine's count) and the threads a run computes with.

A run's intra-op threads (``torch.set_num_threads``) come from, first that is given: ``distilkit run --threads N``
(the recipe's ``threads`` with ``--set``), the recipe's ``threads``, ``OMP_NUM_THREADS`` (which a sweep's ``--jobs``
and torchrun's launcher set for their processes), Slurm's ``SLURM_CPUS_PER_TASK``, and last the CPUs of the
process's affinity mask (``taskset``, a cgroup's cpuset). PyTorch's own default is every core it sees, which on a
machine shared with one other busy process ran about 15x slower than one thread (OpenMP's threads spin-waiting for
the core the other process holds; measured on 2 cores, docs/how-to/reproducibility.md, "Threads")."""

from __future__ import annotations

import os

SOURCES = ("OMP_NUM_THREADS", "SLURM_CPUS_PER_TASK")  # the environment's say, in order


def usable_cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _positive(text: str | None) -> int | None:
    try:
        value = int(str(text).strip().split(",")[0])  # OMP_NUM_THREADS may list nested levels: "4,2"
    except (TypeError, ValueError):
        return None
    return value if value > 0 else None


def default_threads() -> tuple[int, str]:
    """The threads a run uses when neither the command line nor the recipe says, and where the figure comes from:
    ``OMP_NUM_THREADS``, else ``SLURM_CPUS_PER_TASK``, else the CPUs of this process's affinity mask. A count the
    environment names is taken as it is, above the affinity mask's CPUs too, as OpenMP itself takes it."""
    for name in SOURCES:
        value = _positive(os.environ.get(name))
        if value is not None:
            return value, name
    return usable_cpus(), "the CPUs this process may use"


def run_threads(requested: int | None) -> tuple[int, str]:
    """The threads for a run: ``requested`` (``--threads``, the recipe's ``threads``) as given, else
    :func:`default_threads`; with where the figure comes from."""
    if requested is not None:
        return int(requested), "threads"
    return default_threads()


def apply_threads(requested: int | None) -> tuple[int, str]:
    """Set PyTorch's intra-op threads for this process to :func:`run_threads` (``requested`` first) and return it.
    Where nothing names a count (no ``threads``, no ``OMP_NUM_THREADS``, no ``SLURM_CPUS_PER_TASK``) the process's
    count is left as it is: PyTorch's default is then the affinity mask's CPUs already, and a program (a test) that
    set its own count keeps it — raising it in a forked child can hang GNU OpenMP. A change of thread count may
    change a float sum's rounding: each stage's summary records the count."""
    import torch

    threads, source = run_threads(requested)
    if source not in ("threads", *SOURCES):
        return torch.get_num_threads(), "this process's setting"
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return threads, source


__all__ = ["apply_threads", "default_threads", "run_threads", "usable_cpus"]
