"""LiDiff's released checkpoints (PyTorch Lightning, MinkowskiEngine 0.5.4) in the paper-size networks' names and
layout: ``diff_net.ckpt`` holds ``partial_enc.*`` (the scan encoder) and ``model.*`` (MinkUNetDiff), ``refine_net.ckpt``
``model_refine.*``; a convolution's ``kernel`` (kernel volume, in, out) — (in, out) for 1 x 1 x 1 — becomes ``weight``
(out, k0, k1, k2, in) with the offsets reordered (:func:`distilkit.sparse.convert.minkowski_to_spconv2`); batch norms
(``.bn.``) and linear layers keep their names. The adapters prefix ``net.``; ``load_weights`` then names every key
that does not fit (the authors load with ``strict=False``, which would not notice)."""

from __future__ import annotations

from typing import Any

from distilkit.sparse.convert import minkowski_to_spconv2


def from_lightning(weights: dict[str, Any], prefixes: tuple[str, ...]) -> dict[str, Any]:
    """``weights`` as they are when they are distilkit's (``net.*``), else a release's keys under ``prefixes``
    converted (other keys kept, so that a mismatch is named rather than dropped)."""
    if not any(k.startswith(prefixes) for k in weights):
        return weights
    out: dict[str, Any] = {}
    for key, value in weights.items():
        if key.endswith(".kernel") and key.startswith(prefixes):
            out["net." + key[: -len(".kernel")] + ".weight"] = minkowski_to_spconv2(value)
        elif key.startswith(prefixes):
            out["net." + key] = value
        else:
            out[key] = value
    return out


__all__ = ["from_lightning"]
