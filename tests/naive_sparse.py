"""Naive float64 references of the sparse convolutions the released networks ran on, for the parity tests: neighbours
found by dictionary lookups over the active sites' coordinate tuples (not by the library's hashing), one GEMM per
kernel offset.

* :class:`Spconv1` — spconv 1.x (SCPNet / Cylinder3D): weights (k0, k1, k2, in, out); a key's first convolution
  fixes the neighbourhood every later convolution with that key runs on (its own kernel's slices in C order, one per
  stored offset); a strided convolution's pairs are kept under its key for the inverse.
"""

from __future__ import annotations

from itertools import product

import torch
from torch import Tensor

Coords = list[tuple[int, int, int, int]]


def offsets(kernel: tuple[int, ...]) -> list[tuple[int, ...]]:
    return list(product(*(range(k) for k in kernel)))


class Spconv1:
    """The rules of spconv 1.x's SubMConv3d / SparseConv3d / SparseInverseConv3d, by dictionary lookups."""

    def __init__(self) -> None:
        self.kernels: dict[str, tuple[int, int, int]] = {}
        self.strided_maps: dict[str, tuple[Coords, Coords, list[tuple[int, int, int]]]] = {}

    def subm(self, feats: Tensor, coords: Coords, w1: Tensor, key: str) -> Tensor:
        """out[p] = sum_i in[p + o_i - k // 2] @ W[i] over the offsets o_i of the key's first kernel k."""
        kernel = self.kernels.setdefault(key, tuple(w1.shape[:3]))
        flat = w1.reshape(-1, w1.shape[3], w1.shape[4])
        where = {c: n for n, c in enumerate(coords)}
        out = feats.new_zeros(len(coords), w1.shape[4])
        for i, off in enumerate(offsets(kernel)):
            src, dst = [], []
            for n, c in enumerate(coords):
                j = where.get((c[0], c[1] + off[0] - kernel[0] // 2, c[2] + off[1] - kernel[1] // 2,
                               c[3] + off[2] - kernel[2] // 2))
                if j is not None:
                    src.append(j)
                    dst.append(n)
            if src:
                out = out.index_add(0, torch.tensor(dst), feats[src] @ flat[i])
        return out

    def strided(self, feats: Tensor, coords: Coords, shape: tuple[int, int, int], w1: Tensor,
                stride: tuple[int, int, int], pad: tuple[int, int, int], key: str) -> tuple[Tensor, Coords, tuple]:
        """out[o] = sum_i in[o s - p + i] @ W[i] at every output some input reaches (sorted by batch, x, y, z)."""
        kernel = tuple(w1.shape[:3])
        out_shape = tuple((s + 2 * p - k) // st + 1 for s, p, k, st in zip(shape, pad, kernel, stride))
        pairs = []
        for n, c in enumerate(coords):
            for i, off in enumerate(offsets(kernel)):
                num = [c[1 + a] + pad[a] - off[a] for a in range(3)]
                if all(v % st == 0 and 0 <= v // st < o for v, st, o in zip(num, stride, out_shape)):
                    pairs.append((i, n, (c[0],) + tuple(v // st for v, st in zip(num, stride))))
        out_coords = sorted({p[2] for p in pairs})
        row = {c: m for m, c in enumerate(out_coords)}
        flat = w1.reshape(-1, w1.shape[3], w1.shape[4])
        out = feats.new_zeros(len(out_coords), w1.shape[4])
        kept = []
        for i, n, oc in pairs:
            out[row[oc]] = out[row[oc]] + feats[n] @ flat[i]
            kept.append((i, n, row[oc]))
        self.strided_maps[key] = (coords, out_coords, kept)
        return out, out_coords, out_shape

    def inverse(self, feats: Tensor, w1: Tensor, key: str) -> tuple[Tensor, Coords]:
        """Back onto the strided convolution's input sites: out[n] += in[o] @ W[i] for its pairs (i, n, o)."""
        in_coords, _, pairs = self.strided_maps[key]
        flat = w1.reshape(-1, w1.shape[3], w1.shape[4])
        out = feats.new_zeros(len(in_coords), w1.shape[4])
        for i, n, o in pairs:
            out[n] = out[n] + feats[o] @ flat[i]
        return out, in_coords


class SparseConvNet:
    """SparseConvNet's rules (``Metadata/SubmanifoldConvolutionRules.h``, ``ConvolutionRules.h``,
    ``RectangularRegions.h``) by dictionary lookups: weights (filter volume, 1, in, out), the filter index in C order
    (last axis fastest) over the input region of an output — p - 1 .. p + 1 for a 3^3 submanifold convolution,
    2 o .. 2 o + 1 for the size-2 stride-2 convolution — each slice applied as ``features @ W``."""

    @staticmethod
    def subm(feats: Tensor, coords: Coords, w: Tensor) -> Tensor:
        where = {c: n for n, c in enumerate(coords)}
        out = feats.new_zeros(len(coords), w.shape[3])
        for n, c in enumerate(coords):
            for i, d in enumerate(product((-1, 0, 1), repeat=3)):
                j = where.get((c[0], c[1] + d[0], c[2] + d[1], c[3] + d[2]))
                if j is not None:
                    out[n] = out[n] + feats[j] @ w[i, 0]
        return out

    @staticmethod
    def down(feats: Tensor, coords: Coords, w: Tensor) -> tuple[Tensor, Coords, list[tuple[int, int, int]]]:
        """(outputs, their sites (sorted), the pairs (filter index, input row, output row))."""
        out_coords = sorted({(c[0], c[1] // 2, c[2] // 2, c[3] // 2) for c in coords})
        row = {c: m for m, c in enumerate(out_coords)}
        out = feats.new_zeros(len(out_coords), w.shape[3])
        pairs = []
        for n, c in enumerate(coords):
            o = (c[0], c[1] // 2, c[2] // 2, c[3] // 2)
            i = 4 * (c[1] - 2 * o[1]) + 2 * (c[2] - 2 * o[2]) + (c[3] - 2 * o[3])
            out[row[o]] = out[row[o]] + feats[n] @ w[i, 0]
            pairs.append((i, n, row[o]))
        return out, out_coords, pairs

    @staticmethod
    def up(feats: Tensor, pairs: list[tuple[int, int, int]], rows: int, w: Tensor) -> Tensor:
        out = feats.new_zeros(rows, w.shape[3])
        for i, n, o in pairs:
            out[n] = out[n] + feats[o] @ w[i, 0]
        return out
