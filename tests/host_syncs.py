"""The tests' counter of host syncs is the library's (:mod:`distilkit.bench.syncs`, which ``distilkit bench step``
also counts with): on CUDA PyTorch's sync debug mode, on the CPU the ops that would sync there."""

from __future__ import annotations

from distilkit.bench.syncs import SYNCING, host_syncs

__all__ = ["SYNCING", "host_syncs"]
