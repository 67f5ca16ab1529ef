"""Finished runs of another sweep reused by identity (``distilkit sweep FILE --reuse DIR``).

A run's folder is ``<stage>-<hash>``, the hash that of everything that decides the run (the resolved stage and the
stages it reads). A paper's table drawn from a larger comparison — SCPNet's Table 4 from the quickstart's methods —
names its variants otherwise (``kd`` for ``kd_4``), so its folders are other names for the same runs. ``--reuse``
finds, in the folders given (another sweep's output, or its records kept under ``results/``), each finished run
whose summary carries the hash this sweep needs and copies it in under this sweep's name: nothing retrains, and the
copy is the same run (same summary, scores and per-scene counts). Torch-free.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from distilkit.engine.store.summary import read_summary
from distilkit.errors import DistilkitError


def finished_by_hash(folders: list[Path]) -> dict[str, Path]:
    """Every finished run under ``folders`` (one level down), by the hash its summary records; the first folder
    given wins where two hold the same run."""
    found: dict[str, Path] = {}
    for folder in folders:
        if not folder.is_dir():
            raise DistilkitError(f"--reuse {folder}: no such folder (give another sweep's output folder, e.g. "
                                 "runs/quickstart_methods_stored, or its records under results/)")
        for run_dir in sorted(p for p in folder.iterdir() if p.is_dir()):
            summary = read_summary(run_dir)
            if summary is not None and isinstance(summary.get("hash"), str):
                found.setdefault(summary["hash"], run_dir)
    return found


def reuse_runs(run: Any, folders: list[Path]) -> list[tuple[Path, Path]]:
    """Copy into ``run`` (a :class:`~distilkit.sweep.runner.SweepRun`) each run it needs — variants and their
    upstream stages, at every seed — that is not finished here and is finished, with the same hash, under
    ``folders``. A folder here that holds a stopped run of that name is left alone (the sweep resumes it). Returns
    the (source, copy) pairs."""
    found = finished_by_hash(folders)
    copied: list[tuple[Path, Path]] = []
    for (variant, _seed), pipe in run.pipes.items():
        for name in [*run.sweep.upstream_stages(variant), variant]:
            target = pipe.run_dir(name)
            source = found.get(pipe.hashes[name])
            if source is None or target.exists() or source.resolve() == target.resolve():
                continue
            partial = target.with_name(target.name + ".reusing")
            shutil.rmtree(partial, ignore_errors=True)
            shutil.copytree(source, partial, ignore=shutil.ignore_patterns("*.lock"))
            os.replace(partial, target)  # whole or not at all: a stop mid-copy leaves no half run under the name
            copied.append((source, target))
    return copied


__all__ = ["finished_by_hash", "reuse_runs"]
