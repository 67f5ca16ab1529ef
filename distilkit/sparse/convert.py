"""Sparse-convolution weights of other libraries in spconv 2.2+'s layout (out, k0, k1, k2, in), the one
:mod:`distilkit.sparse` uses, and back (to write a file in another library's layout, e.g. for tests):

* spconv 1.x: (k0, k1, k2, in, out); spconv 2.0: (k0, k1, k2, out, in);
* MinkowskiEngine 0.5: ``kernel`` (kernel volume, in, out), the kernel index running over the offsets with the *first*
  axis fastest (``kernel_region.hpp``: axis i's index is k % k_i, then k //= k_i), and a 1 x 1 x 1 stride-1 kernel
  stored 2-D (in, out). Odd kernels are centred (offset i - k // 2), even ones start at the site (offset i), which is
  also :mod:`distilkit.sparse`'s convention for a stride-k, kernel-k convolution.
"""

from __future__ import annotations

from typing import Sequence

from torch import Tensor


def spconv1_to_spconv2(w: Tensor) -> Tensor:
    """(k0, k1, k2, in, out) -> (out, k0, k1, k2, in)."""
    return w.permute(4, 0, 1, 2, 3).contiguous()


def spconv2_to_spconv1(w: Tensor) -> Tensor:
    return w.permute(1, 2, 3, 4, 0).contiguous()


def spconv20_to_spconv2(w: Tensor) -> Tensor:
    """spconv 2.0's (k0, k1, k2, out, in) -> (out, k0, k1, k2, in)."""
    return w.permute(3, 0, 1, 2, 4).contiguous()


def cube(volume: int) -> tuple[int, int, int]:
    """The cubic kernel of ``volume`` offsets (1, 8, 27, 125, ...)."""
    k = round(volume ** (1 / 3))
    if k ** 3 != volume:
        raise ValueError(f"a MinkowskiEngine kernel of {volume} offsets is not a cube (give the kernel size)")
    return k, k, k


def minkowski_to_spconv2(kernel: Tensor, kernel_size: Sequence[int] | None = None) -> Tensor:
    """A MinkowskiEngine ``kernel`` ((K, in, out), or (in, out) for 1 x 1 x 1) -> (out, k0, k1, k2, in)."""
    if kernel.dim() == 2:
        kernel = kernel[None]
    k0, k1, k2 = tuple(kernel_size) if kernel_size is not None else cube(kernel.shape[0])
    if k0 * k1 * k2 != kernel.shape[0]:
        raise ValueError(f"kernel of {kernel.shape[0]} offsets for a {k0}x{k1}x{k2} kernel")
    # kernel index k = i0 + k0 (i1 + k1 i2): view as (k2, k1, k0, in, out) and reverse the offset axes
    w = kernel.reshape(k2, k1, k0, kernel.shape[1], kernel.shape[2])
    return w.permute(4, 2, 1, 0, 3).contiguous()


def spconv2_to_minkowski(w: Tensor, flat_1x1: bool = True) -> Tensor:
    """(out, k0, k1, k2, in) -> MinkowskiEngine's (K, in, out) (a 1 x 1 x 1 kernel as (in, out) when ``flat_1x1``)."""
    out, k0, k1, k2, inc = w.shape
    kernel = w.permute(3, 2, 1, 4, 0).reshape(k0 * k1 * k2, inc, out).contiguous()
    return kernel[0] if flat_1x1 and kernel.shape[0] == 1 else kernel


__all__ = ["cube", "minkowski_to_spconv2", "spconv1_to_spconv2", "spconv20_to_spconv2", "spconv2_to_minkowski",
           "spconv2_to_spconv1"]
