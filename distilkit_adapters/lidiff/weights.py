"""LiDiff's released checkpoints (PyTorch Lightning, MinkowskiEngine 0.5.4) in the paper-size networks' names and
layout: ``diff_net.ckpt`` holds ``partial_enc.*`` (the scan encoder) and ``model.*`` (MinkUNetDiff), ``refine_net.ckpt``
``model_refine.*``; a convolution's ``kernel`` (kernel volume, in, out) — (in, out) for 1 x 1 x 1 — becomes ``weight``
(out, k0, k1, k2, in) with the offsets reordered (:func:`distilkit.sparse.convert.minkowski_to_spconv2`); batch norms
(``.bn.``) and linear layers keep their names. The adapters prefix ``net.``; ``load_weights`` then names every key
that does not fit (the authors load with ``strict=False``, which would not notice), as the model calls it and as the
file spells it (``model.up1.1.0.downsample.0.kernel``)."""

from __future__ import annotations

from typing import Any

from distilkit.weights import ImportedWeights
from distilkit.errors import DataError
from distilkit.sparse.convert import minkowski_to_spconv2


def _kernel(key: str, value: Any) -> Any:
    """A MinkowskiEngine kernel as (out, k0, k1, k2, in), or a DataError naming the key."""
    shape = tuple(value.shape)
    if value.dim() not in (2, 3):
        raise DataError(f"{key}: a MinkowskiEngine kernel is (kernel volume, in, out), or (in, out) for 1 x 1 x 1; "
                        f"this one is {shape}")
    try:
        return minkowski_to_spconv2(value)
    except ValueError as exc:
        raise DataError(f"{key}: {shape}: {exc}") from None


def _file_name(key: str, shape: tuple[int, ...]) -> str:
    """How a release spells a model key it lacks: no ``net.``, a sparse convolution's 5-D weight as ``kernel``."""
    bare = key[len("net."):] if key.startswith("net.") else key
    return bare[: -len(".weight")] + ".kernel" if len(shape) == 5 and bare.endswith(".weight") else bare


def from_lightning(weights: dict[str, Any], prefixes: tuple[str, ...]) -> dict[str, Any]:
    """``weights`` as they are when they are distilkit's (``net.*``), else a release's keys under ``prefixes``
    converted (other keys kept, so that a mismatch is named rather than dropped)."""
    if not any(k.startswith(prefixes) for k in weights):
        return weights
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    for key, value in weights.items():
        if key.endswith(".kernel") and key.startswith(prefixes):
            name = "net." + key[: -len(".kernel")] + ".weight"
            out[name] = _kernel(key, value)
        else:
            name = "net." + key if key.startswith(prefixes) else key
            out[name] = value
        spelled[name] = key
    return ImportedWeights(out, spelled, _file_name)


__all__ = ["from_lightning"]
