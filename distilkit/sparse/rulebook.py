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
    def pairs_host(self) -> int:
        """The number of pairs, read from the host-side bounds (no device sync)."""
        return self.bounds[-1] - self.bounds[0]

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


def triple(v: int | Sequence[int], name: str, minimum: int | None = None, who: str = "") -> Triple:
    """Three ints from ``v``, an integer for all three axes or a sequence of three (spconv's ``kernel_size``,
    ``stride``, ``padding``, ``dilation``). An integer is a Python int, a numpy integer or a 0-d integer tensor; a
    bool, a float or a string is a ``TypeError``, a length other than 3 or (with ``minimum``) a value below
    ``minimum`` a ``ValueError``, each naming ``name`` and the value, after ``who`` (the caller, e.g. the layer)."""
    import operator

    def integer(x: object) -> int | None:
        if isinstance(x, bool) or (isinstance(x, Tensor) and (x.dim() != 0 or x.dtype == torch.bool)):
            return None
        try:
            return operator.index(x)  # type: ignore[arg-type]
        except TypeError:
            return None

    what = ("an integer" if minimum is None else "a positive integer" if minimum == 1 else
            f"an integer >= {minimum}")
    expected = f"{who + ': ' if who else ''}{name} must be {what} or three of them (a tuple or list)"
    one = integer(v)
    if one is not None:
        t: tuple[int, ...] = (one, one, one)
    else:
        if isinstance(v, (str, bytes)) or (isinstance(v, Tensor) and v.dim() == 0) or not hasattr(v, "__iter__"):
            raise TypeError(f"{expected}, got {v!r} ({type(v).__name__})")
        items = list(v)  # type: ignore[call-overload]
        if len(items) != 3:
            raise ValueError(f"{expected}, got {len(items)} values: {v!r}")
        ints = [integer(x) for x in items]
        bad = [x for x, i in zip(items, ints) if i is None]
        if bad:
            raise TypeError(f"{expected}, got {v!r} ({bad[0]!r} is a {type(bad[0]).__name__}, not an integer)")
        t = tuple(ints)  # type: ignore[arg-type]
    if minimum is not None and min(t) < minimum:
        raise ValueError(f"{expected}, got {v!r}")
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


def sort_keys(indices: Tensor, shape: Sequence[int]) -> tuple[Tensor, Tensor]:
    """(sorted keys, the stable sort's permutation) of (N, 4) indices inside the grid ``shape``."""
    return torch.sort(keys(indices, shape), stable=True)


CHUNK = 1 << 21  # (kernel offsets x sites) looked up at once: a few tens of MB of int64, two host syncs a chunk


def _chunks(volume: int, sites: int) -> list[range]:
    """Kernel offsets in groups of about :data:`CHUNK` (offset, site) pairs each."""
    step = max(1, CHUNK // max(sites, 1))
    return [range(s, min(s + step, volume)) for s in range(0, volume, step)]


def _offset_rows(kernel: Triple, chunk: range, device: torch.device) -> Tensor:
    """(len(chunk), 3) int64: the kernel indices (i0, i1, i2) of offsets ``chunk`` in C order, made on ``device`` (no
    host-to-device copy, which CUDA counts as a sync)."""
    i = torch.arange(chunk.start, chunk.stop, device=device)
    return torch.stack([i // (kernel[1] * kernel[2]), (i // kernel[2]) % kernel[1], i % kernel[2]], dim=1)


def _bounds(counts: list[Tensor]) -> list[int]:
    """Boundaries of the offsets' pairs from their counts, read to the host once."""
    bounds = [0]
    for c in torch.cat(counts).tolist() if counts else []:
        bounds.append(bounds[-1] + int(c))
    return bounds


def submanifold(indices: Tensor, shape: Sequence[int], kernel: Triple, dilation: Triple,
                sorted_keys: tuple[Tensor, Tensor] | None = None) -> Rulebook:
    """Submanifold convolution's map: outputs at the inputs' sites, each reading its neighbours at the kernel's
    offsets about the centre (odd kernels). ``sorted_keys``: :func:`sort_keys` of ``indices``, when known.

    All offsets of a chunk are looked up at once, so a map costs two host syncs a chunk (the found pairs' positions
    and, at the end, the counts), not a few per offset; the pairs come out in the same order (offset, then site)."""
    if any(k % 2 == 0 for k in kernel):
        raise ValueError(f"a submanifold convolution needs an odd kernel (centred on each site), got {kernel}")
    device = indices.device
    shape = tuple(int(s) for s in shape)
    sorted_keys, order = sorted_keys if sorted_keys is not None else sort_keys(indices, shape)
    coords = indices.long()
    n_sites = coords.shape[0]
    rows = torch.arange(n_sites, device=device)
    offsets = _offsets(kernel)
    deltas = [tuple((o - (k - 1) // 2) * d for o, k, d in zip(off, kernel, dilation)) for off in offsets]
    ins, outs, counts = [], [], []
    for chunk in _chunks(len(deltas), n_sites):
        o = _offset_rows(kernel, chunk, device)
        delta = torch.stack([(o[:, a] - (kernel[a] - 1) // 2) * dilation[a] for a in range(3)], dim=1)
        n = coords[None, :, 1:] + delta[:, None, :]  # (c, N, 3) the neighbours' coordinates
        inside = (n >= 0).all(dim=2) & (n[..., 0] < shape[0]) & (n[..., 1] < shape[1]) & (n[..., 2] < shape[2])
        query = ((coords[None, :, 0] * shape[0] + n[..., 0]) * shape[1] + n[..., 1]) * shape[2] + n[..., 2]
        src, found = _lookup(sorted_keys, order, query.reshape(-1))
        src, valid = src.view(len(chunk), n_sites), (found.view(len(chunk), n_sites) & inside)
        for j, i in enumerate(chunk):
            if not any(deltas[i]):  # the centre: every site with itself (duplicates included)
                src[j], valid[j] = rows, True
        kk, rr = valid.nonzero(as_tuple=True)
        ins.append(src[kk, rr])
        outs.append(rr)
        counts.append(valid.sum(dim=1))
    bounds = _bounds(counts)
    in_idx = torch.cat(ins) if ins else rows[:0]
    out_idx = torch.cat(outs) if outs else rows[:0]
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
    rows ordered by (batch, x, y, z). The offsets of a chunk at once (as :func:`submanifold`)."""
    device = indices.device
    shape = tuple(int(s) for s in shape)
    out_shape = output_shape(shape, kernel, stride, padding, dilation)
    coords = indices.long()
    n_sites = coords.shape[0]
    rows = torch.arange(n_sites, device=device)
    offsets = _offsets(kernel)
    src_rows, out_coords, counts = [], [], []
    for chunk in _chunks(len(offsets), n_sites):
        off = _offset_rows(kernel, chunk, device)
        axes, ok = [], None
        for a in range(3):  # per axis, with Python numbers: no small tensors copied to the device
            num = coords[None, :, 1 + a] + padding[a] - off[:, a, None] * dilation[a]  # (c, N)
            o_a = torch.div(num, stride[a], rounding_mode="floor")
            fits = ((num % stride[a]) == 0) & (o_a >= 0) & (o_a < out_shape[a])
            ok = fits if ok is None else ok & fits
            axes.append(o_a)
        o = torch.stack(axes, dim=2)
        kk, rr = ok.nonzero(as_tuple=True)
        src_rows.append(rr)
        out_coords.append(torch.cat([coords[rr, :1], o[kk, rr]], dim=1))
        counts.append(ok.sum(dim=1))
    bounds = _bounds(counts)
    all_out = torch.cat(out_coords) if out_coords else coords.new_zeros((0, 4))
    all_keys = keys(all_out, out_shape)
    out_keys = torch.unique(all_keys) if all_out.numel() else all_out.new_zeros((0,))
    out_indices = _from_keys(out_keys, out_shape)
    in_idx = torch.cat(src_rows) if src_rows else rows[:0]
    out_idx = torch.searchsorted(out_keys, all_keys)
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
