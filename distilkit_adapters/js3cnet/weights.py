"""JS3C-Net's released checkpoint (yanx27/JS3C-Net, ``log/JS3C-Net-kitti/model_*.pth``) in the paper-size network's
names: a bare ``state_dict()`` of the release's ``J3SC_Net`` (no ``module.`` prefix), ``seg_head.*`` (its
SparseConvNet weights in scn's own layout, which :mod:`.scn` keeps) and ``complet_head.*``, prefixed ``net.``.
The file also holds what is not the network's, reported as left out by design: ``voxelpool.*`` (the
release builds it whenever ``fuse_k > 1`` but uses it only with ``pooling_type: relation``; the checkpoint's is
``mean``) and ``seg_sigmas_sq`` / ``complet_sigmas_sq`` (the uncertainty loss's weights, a task loss's parameters
here). ``load_weights`` names every other key that does not fit, as the model calls it and as the file spells it."""

from __future__ import annotations

from typing import Any

from distilkit.weights import under_prefix

PREFIXES = ("seg_head.", "complet_head.")
NOT_THE_NETWORK = {"voxelpool.": "unused with pooling_type: mean", "seg_sigmas_sq": "the uncertainty loss's weight",
                   "complet_sigmas_sq": "the uncertainty loss's weight"}


def from_release(weights: dict[str, Any]) -> dict[str, Any]:
    """``weights`` as they are when they are distilkit's, else the release's under the network's names."""
    return under_prefix(weights, PREFIXES, NOT_THE_NETWORK)


__all__ = ["from_release"]
