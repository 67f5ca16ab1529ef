"""The CPUs this process may use (its affinity mask, not the machine's count): what parallel runs split."""

from __future__ import annotations

import os


def usable_cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


__all__ = ["usable_cpus"]
