"""Neighbour maps (rulebooks) of sparse 3-D convolutions, built by voxel hashing: for every kernel offset, the pairs
(input row, output row) it connects. Nothing dense is ever allocated: keys of (batch, x, y, z) are sorted once and
looked up with ``searchsorted``.

Conventions (those of ``torch.nn.functional.conv3d`` and spconv): a kernel index i = (i0, i1, i2) in C order, and

* submanifold (``SubMConv3d``, odd kernel): out[p] = sum_i W_i in[p + (i - (k - 1) / 2) d], outputs at the inputs'
  sites only;
* strided (``SparseConv3d``): out[o] = sum_i W_i in[o s - p + i d] on the output grid of size
  floor((X + 2p - d (k - 1) - 1) / s) + 1, active where some active input reaches;
* inverse (``SparseInverseConv3d``): the transpose of a strided convolution's map, back onto its input sites:
  out[n] = sum_{o, i : n = o s - p + i d} W_i in[o] (``conv_transpose3d`` restricted to those sites).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Sequence

import torch
from torch import Tensor

Triple = tuple[int, int, int]


@dataclass
class Rulebook:
    """The pairs of one convolution: for kernel index k (C order), rows ``in_idx[bounds[k]:bounds[k+1]]`` of the
    input feed rows ``out_idx[...]`` of the output; the output's sites and grid; the input's, to invert it."""

    in_idx: Tensor  # (P,) int64
    out_idx: Tensor  # (P,) int64
    bounds: list[int]  # (K + 1,) boundaries of each kernel index's pairs
    out_indices: Tensor  # (M, 4) int32 (batch, x, y, z)
    out_shape: Triple
    in_indices: Tensor  # (N, 4) int32
    in_shape: Triple
    kernel: Triple
    dilation: Triple = (1, 1, 1)
    subm: bool = False  # a submanifold map (outputs at the input's sites), else a strided one or its inverse
    cache: dict = field(default_factory=dict, repr=False, compare=False)  # derived forms (its inverse, spconv's pairs)

    @property
    def pairs(self) -> int:
        return int(self.in_idx.numel())

    @property
    def volume(self) -> int:
        """The number of kernel offsets the map holds."""
        return len(self.bounds) - 1

    def inverse(self) -> "Rulebook":
        """The map back: the output's rows feed the input's sites, kernel index by kernel index (built once)."""
        if "inverse" not in self.cache:
            self.cache["inverse"] = Rulebook(self.out_idx, self.in_idx, self.bounds, self.in_indices, self.in_shape,
                                             self.out_indices, self.out_shape, self.kernel, self.dilation)
        return self.cache["inverse"]


def triple(v: int | Sequence[int], name: str) -> Triple:
    t = (v, v, v) if isinstance(v, int) else tuple(int(x) for x in v)
    if len(t) != 3:
        raise ValueError(f"{name} must be an int or three ints, got {v}")
    return t  # type: ignore[return-value]


def keys(indices: Tensor, shape: Sequence[int]) -> Tensor:
    """int64 key ((b X + x) Y + y) Z + z of (N, 4) indices (inside the grid)."""
    c = indices.long()
    return ((c[:, 0] * shape[0] + c[:, 1]) * shape[1] + c[:, 2]) * shape[2] + c[:, 3]


def _lookup(sorted_keys: Tensor, order: Tensor, query: Tensor) -> tuple[Tensor, Tensor]:
    """(rows, found) of ``query`` keys among sorted keys (``order``: the sort's permutation)."""
    if sorted_keys.numel() == 0:
        return torch.zeros_like(query), torch.zeros_like(query, dtype=torch.bool)
    pos = torch.searchsorted(sorted_keys, query).clamp_max(sorted_keys.numel() - 1)
    return order[pos], sorted_keys[pos] == query


def _offsets(kernel: Triple) -> list[Triple]:
    return list(product(range(kernel[0]), range(kernel[1]), range(kernel[2])))


def _assemble(ins: list[Tensor], outs: list[Tensor]) -> tuple[Tensor, Tensor, list[int]]:
    bounds = [0]
    for t in ins:
        bounds.append(bounds[-1] + int(t.numel()))
    return torch.cat(ins), torch.cat(outs), bounds


def sort_keys(indices: Tensor, shape: Sequence[int]) -> tuple[Tensor, Tensor]:
    """(sorted keys, the stable sort's permutation) of (N, 4) indices inside the grid ``shape``."""
    return torch.sort(keys(indices, shape), stable=True)


def submanifold(indices: Tensor, shape: Sequence[int], kernel: Triple, dilation: Triple,
                sorted_keys: tuple[Tensor, Tensor] | None = None) -> Rulebook:
    """Submanifold convolution's map: outputs at the inputs' sites, each reading its neighbours at the kernel's
    offsets about the centre (odd kernels). ``sorted_keys``: :func:`sort_keys` of ``indices``, when known."""
    if any(k % 2 == 0 for k in kernel):
        raise ValueError(f"a submanifold convolution needs an odd kernel (centred on each site), got {kernel}")
    device = indices.device
    shape = tuple(int(s) for s in shape)
    sorted_keys, order = sorted_keys if sorted_keys is not None else sort_keys(indices, shape)
    coords = indices.long()
    rows = torch.arange(coords.shape[0], device=device)
    ins, outs = [], []
    size = torch.tensor(shape, device=device)
    for off in _offsets(kernel):
        delta = torch.tensor([(o - (k - 1) // 2) * d for o, k, d in zip(off, kernel, dilation)], device=device)
        if not bool(delta.any()):  # the centre: every site with itself
            ins.append(rows)
            outs.append(rows)
            continue
        n = coords[:, 1:] + delta
        inside = ((n >= 0) & (n < size)).all(dim=1)
        query = ((coords[inside, 0] * shape[0] + n[inside, 0]) * shape[1] + n[inside, 1]) * shape[2] + n[inside, 2]
        src, found = _lookup(sorted_keys, order, query)
        ins.append(src[found])
        outs.append(rows[inside][found])
    in_idx, out_idx, bounds = _assemble(ins, outs)
    return Rulebook(in_idx, out_idx, bounds, indices, shape, indices, shape, kernel, dilation,  # type: ignore[arg-type]
                    subm=True)


def output_shape(shape: Sequence[int], kernel: Triple, stride: Triple, padding: Triple, dilation: Triple) -> Triple:
    out = tuple((int(x) + 2 * p - d * (k - 1) - 1) // s + 1
                for x, k, s, p, d in zip(shape, kernel, stride, padding, dilation))
    if any(o < 1 for o in out):
        raise ValueError(f"the convolution leaves no output voxel: input grid {tuple(shape)}, kernel {kernel}, "
                         f"stride {stride}, padding {padding}, dilation {dilation}")
    return out  # type: ignore[return-value]


def strided(indices: Tensor, shape: Sequence[int], kernel: Triple, stride: Triple, padding: Triple,
            dilation: Triple) -> Rulebook:
    """A regular (strided) convolution's map: every output site some active input reaches (o s = n + p - i d), its
    rows ordered by (batch, x, y, z)."""
    device = indices.device
    shape = tuple(int(s) for s in shape)
    out_shape = output_shape(shape, kernel, stride, padding, dilation)
    coords = indices.long()
    rows = torch.arange(coords.shape[0], device=device)
    s, p, d = (torch.tensor(v, device=device) for v in (stride, padding, dilation))
    size = torch.tensor(out_shape, device=device)
    cand: list[tuple[Tensor, Tensor]] = []  # per kernel index: (input rows, output coordinates)
    for off in _offsets(kernel):
        num = coords[:, 1:] + p - torch.tensor(off, device=device) * d
        o = torch.div(num, s, rounding_mode="floor")
        ok = ((num % s) == 0).all(dim=1) & ((o >= 0) & (o < size)).all(dim=1)
        cand.append((rows[ok], torch.cat([coords[ok, :1], o[ok]], dim=1)))
    all_out = torch.cat([c for _, c in cand]) if cand else coords.new_zeros((0, 4))
    out_keys = torch.unique(keys(all_out, out_shape)) if all_out.numel() else all_out.new_zeros((0,))
    out_indices = _from_keys(out_keys, out_shape)
    ins, outs = [], []
    for src, oc in cand:
        ins.append(src)
        outs.append(torch.searchsorted(out_keys, keys(oc, out_shape)))
    in_idx, out_idx, bounds = _assemble(ins, outs) if ins else (rows[:0], rows[:0], [0])
    return Rulebook(in_idx, out_idx, bounds, out_indices, out_shape, indices, shape, kernel,  # type: ignore[arg-type]
                    dilation)


def _from_keys(k: Tensor, shape: Sequence[int]) -> Tensor:
    """(M, 4) int32 indices of sorted keys."""
    x, y, z = shape
    out = torch.empty((k.numel(), 4), dtype=torch.int64, device=k.device)
    out[:, 3] = k % z
    r = k // z
    out[:, 2] = r % y
    r = r // y
    out[:, 1] = r % x
    out[:, 0] = r // x
    return out.int()


__all__ = ["Rulebook", "keys", "output_shape", "sort_keys", "strided", "submanifold", "triple"]
