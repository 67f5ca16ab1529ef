"""JS3C-Net's released checkpoint (yanx27/JS3C-Net, ``log/JS3C-Net-kitti/model_*.pth``) in the paper-size network's
names: a bare ``state_dict()`` of the release's ``J3SC_Net`` (no ``module.`` prefix), ``seg_head.*`` (its
SparseConvNet weights in scn's own layout, which :mod:`.scn` keeps) and ``complet_head.*``, prefixed ``net.``.
The file also holds what is not the network's, reported as left out by design: ``voxelpool.relation_w.*`` (the
release builds it whenever ``fuse_k > 1`` but uses it only with ``pooling_type: relation``; the checkpoint's is
``mean``) and ``seg_sigmas_sq`` / ``complet_sigmas_sq`` (the uncertainty loss's weights, a task loss's parameters
here). ``load_weights`` names every other key that does not fit, as the model calls it and as the file spells it."""

from __future__ import annotations

from typing import Any

from distilkit.engine.checkpoints import ImportedWeights

PREFIXES = ("seg_head.", "complet_head.")
NOT_THE_NETWORK = {"voxelpool.": "unused with pooling_type: mean", "seg_sigmas_sq": "the uncertainty loss's weight",
                   "complet_sigmas_sq": "the uncertainty loss's weight"}


def _file_name(key: str, shape: tuple[int, ...]) -> str:
    return key[len("net."):] if key.startswith("net.") else key


def from_release(weights: dict[str, Any]) -> dict[str, Any]:
    """``weights`` as they are when they are distilkit's, else the release's under the network's names."""
    if not any(k.startswith(PREFIXES) for k in weights):
        return weights
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    ignored: list[str] = []
    for key, value in weights.items():
        why = next((w for prefix, w in NOT_THE_NETWORK.items() if key.startswith(prefix)), None)
        if why is not None:
            ignored.append(f"{key} ({why})")
            continue
        name = "net." + key if key.startswith(PREFIXES) else key
        out[name] = value
        spelled[name] = key
    return ImportedWeights(out, spelled, _file_name, tuple(ignored))


__all__ = ["from_release"]
