"""The on-disk cache of generated samples (synthetic streets and LiDiff-style scenes): one ``.npz`` per split,
named by a hash of the generator's parameters and version, under ``$DISTILKIT_CACHE`` (default
``~/.cache/distilkit``); entries are written atomically and a corrupt one is regenerated."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

from distilkit.files import cache_root


def content_key(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def cached_samples(kind: str, version: int, params: dict[str, Any], split: str, count: int,
                   make: Callable[[int], dict[str, np.ndarray]],
                   stack: Callable[[list[dict[str, np.ndarray]]], dict[str, np.ndarray]],
                   progress: Callable[[int, int], None] | None = None) -> dict[str, np.ndarray]:
    """``count`` samples of ``split`` made by ``make(seed)`` (seeds from the data seed ``params["seed"]`` and the
    split) and stacked, cached on disk under ``kind`` by the content of ``params`` (the generator's parameters that
    shape these arrays), ``version`` and the split."""
    key = content_key({"v": version, "split": split, "count": count, **params})
    path = cache_root() / kind / f"{split}-{key}.npz"
    cached = read_cached(path)
    if cached is not None:
        return cached
    samples = []
    for i in range(count):
        samples.append(make(sample_seed(int(params["seed"]), split, i)))
        if progress:
            progress(i + 1, count)
    out = stack(samples)
    write_cached(path, out)
    return out


def sample_seed(data_seed: int, split: str, i: int) -> int:
    """The generator seed of sample ``i`` of ``split`` (every generator of the same scenes draws them alike)."""
    salt = {"train": 0, "val": 1, "test": 2}.get(split, 3)
    return data_seed * 1_000_003 + salt * 100_003 + i


def read_cached(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache entry, or None when there is none; a corrupt entry is removed (and regenerated)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception:
        path.unlink(missing_ok=True)
        return None


def write_cached(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a cache entry atomically (a temporary file renamed into place)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)
