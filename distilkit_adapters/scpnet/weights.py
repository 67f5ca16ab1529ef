"""SCPNet's released weights (SCPNet/Codes-for-SCPNet, on Cylinder3D) in the paper-size network's names and layout.

The release saves a bare state dict (``torch.save(model.state_dict())``; a ``module.`` prefix from DataParallel is
dropped if present) of ``cylinder_asym``: ``cylinder_3d_generator.*`` and ``cylinder_3d_spconv_seg.*``. Its sparse
convolutions are spconv 1.x's, weights (k0, k1, k2, in, out) (its requirements pin spconv 1.2.1); a file saved with
spconv 2.2+ has (out, k0, k1, k2, in) and is taken as it is. Which one a weight is follows from its shape (the kernel
sizes are at most 7, the channels above): a shape that fits both layouts (channels of 7 or fewer) is refused rather
than guessed; spconv 2.0's (k0, k1, k2, out, in) is read as 1.x, as SCPNet's release cannot hold it. The dense
completion convolutions (``a_conv*``, ``ch_conv1``, ``res_*``) are ``nn.Conv3d`` and stay as they are. The adapter
prefixes ``net.``; ``load_weights`` names every key that does not fit.
"""

from __future__ import annotations

from functools import partial
from typing import Any

from distilkit.weights import ImportedWeights
from distilkit.errors import DataError
from distilkit.sparse.convert import spconv1_to_spconv2

PREFIXES = ("cylinder_3d_generator.", "cylinder_3d_spconv_seg.")
DENSE = ("a_conv", "ch_conv", "res_")  # the completion sub-network's nn.Conv3d modules


def sparse_layout(key: str, shape: tuple[int, ...]) -> str:
    """"1.x" (k0, k1, k2, in, out) or "2.x" (out, k0, k1, k2, in) of a sparse convolution's weight."""
    one = all(s <= 7 for s in shape[:3]) and not all(s <= 7 for s in shape[1:4])
    two = all(s <= 7 for s in shape[1:4]) and not all(s <= 7 for s in shape[:3])
    if one == two:
        raise DataError(f"{key}: weight {tuple(shape)} fits both spconv 1.x's (k0, k1, k2, in, out) and 2.x's "
                        "(out, k0, k1, k2, in) layout; convert it to one of them first")
    return "1.x" if one else "2.x"


def _file_name(lead: str, key: str, shape: tuple[int, ...]) -> str:
    """How the release spells a model key it lacks: no ``net.``, its DataParallel prefix if it had one."""
    return lead + (key[len("net."):] if key.startswith("net.") else key)


def from_release(weights: dict[str, Any]) -> dict[str, Any]:
    """``weights`` as they are when they are distilkit's, else the release's converted (see the module)."""
    prefixed = any(k.startswith("module.") for k in weights)
    stripped = {k[len("module."):] if k.startswith("module.") else k: v for k, v in weights.items()}
    if not any(k.startswith(PREFIXES) for k in stripped):
        return weights
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    for key, value in stripped.items():
        module = key.split(".")[1] if key.startswith("cylinder_3d_spconv_seg.") else ""
        if (key.startswith("cylinder_3d_spconv_seg.") and key.endswith(".weight") and value.dim() == 5
                and not module.startswith(DENSE)):
            if sparse_layout(key, tuple(value.shape)) == "1.x":
                value = spconv1_to_spconv2(value)
        name = ("net." + key) if key.startswith(PREFIXES) else key
        out[name] = value
        spelled[name] = ("module." if prefixed else "") + key
    return ImportedWeights(out, spelled, partial(_file_name, "module." if prefixed else ""))


__all__ = ["from_release", "sparse_layout"]
