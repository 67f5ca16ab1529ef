"""``SparseConvTensor``: active voxels of a batch of 3-D grids, as spconv 2.x holds them.

``features`` (N, C), ``indices`` int32 (N, 4) = (batch, x, y, z), ``spatial_shape`` (X, Y, Z) and ``batch_size``;
``indice_dict`` keeps the neighbour maps (rulebooks) of the convolutions that ran on it by their ``indice_key``, so a
later submanifold convolution with the same key, or the inverse of a strided one, reuses them instead of hashing
again (spconv's contract: a tensor and the ones derived from it by ``replace_feature`` share the dictionary).
With ``semantics="spconv1"`` a convolution also *writes* its maps into the dictionary of the tensor it was given, so
a second model run on the same tensor reuses the first one's maps (as spconv 1.x does): give it ``x.fresh()``, the
same voxels and features with an empty dictionary.

The arguments are checked when the tensor is built, as ``torch.nn.Conv3d`` checks its own: floating ``features``, a
torch integer (int32 or int64) tensor of ``indices`` (a numpy array or a list is a ``TypeError`` naming its type:
they are not converted, so the caller chooses the device and no copy is shared with an array changed later), three
positive integer sizes of ``spatial_shape`` (a float is refused, not truncated) and an integer ``batch_size`` >= 0 (0:
an empty batch, as ``from_dense`` makes of a (0, C, X, Y, Z) grid and ``torch.nn.Conv3d`` takes; it can hold no
voxel). Integers may be numpy integers or 0-d integer tensors; a bool is not an integer.

A tensor built from outside (not derived by a convolution or ``replace_feature``) has its indices checked, O(N) and
one sort: every batch index in [0, batch_size), every coordinate in [0, spatial_shape), no voxel twice. spconv
accepts all three silently, and each changes the result (a duplicate's copies get different outputs; a coordinate
past the grid lands on the next batch's voxels). The sort is kept for the first submanifold map built on the
tensor, which would sort the same keys.
"""

from __future__ import annotations

import operator
from typing import Any

import torch
from torch import Tensor

from distilkit.sparse.rulebook import sort_keys


class SparseConvTensor:
    """A batch of sparse 3-D grids (spconv 2.x's API)."""

    def __init__(self, features: Tensor, indices: Tensor, spatial_shape: Any, batch_size: int,
                 indice_dict: dict[str, Any] | None = None, *, _checked: bool = False) -> None:
        shape = _spatial_shape(spatial_shape)
        batch = as_int(batch_size, "batch_size", 0, "SparseConvTensor")
        if not isinstance(features, Tensor):
            raise TypeError(f"SparseConvTensor: features must be a floating torch tensor (N, C), got "
                            f"{_type_name(features)}{_numpy_hint(features, 'torch.from_numpy(features).float()')}")
        if not features.is_floating_point():
            raise TypeError(f"SparseConvTensor: features must be floating (float32, float64, float16 or bfloat16), "
                            f"got {features.dtype} (convert them: features.float())")
        if not isinstance(indices, Tensor):
            hint = _numpy_hint(indices, "torch.from_numpy(indices).int(), on the features' device")
            raise TypeError(f"SparseConvTensor: indices must be a torch integer tensor (N, 4) = (batch, x, y, z), "
                            f"got {_type_name(indices)}{hint}")
        if indices.dtype not in (torch.int32, torch.int64):
            raise TypeError(f"SparseConvTensor: indices must be an int32 (or int64) tensor, got {indices.dtype}")
        if features.dim() != 2:
            raise ValueError(f"SparseConvTensor: features must be (N, C), got {tuple(features.shape)}")
        if indices.dim() != 2 or indices.shape[1] != 4 or indices.shape[0] != features.shape[0]:
            raise ValueError(f"SparseConvTensor: indices must be (N, 4) = (batch, x, y, z) for N = "
                             f"{features.shape[0]} features, got {tuple(indices.shape)}")
        self.features = features
        self.indices = indices
        self.spatial_shape = list(shape)
        self.batch_size = batch
        self.indice_dict: dict[str, Any] = {} if indice_dict is None else indice_dict
        # (sorted keys, permutation) of the indices, when the check below sorted them
        self.sorted_keys: tuple[Tensor, Tensor] | None = None if _checked else check_indices(indices, shape,
                                                                                              self.batch_size)

    def derived(self, features: Tensor, indices: Tensor | None = None, spatial_shape: Any = None,
                indice_dict: dict[str, Any] | None = None) -> "SparseConvTensor":
        """A tensor computed from this one (a layer's output): its indices are not checked again; the same indices
        keep the sorted keys."""
        same = indices is None or indices is self.indices
        out = SparseConvTensor(features, self.indices if indices is None else indices,
                               self.spatial_shape if spatial_shape is None else spatial_shape, self.batch_size,
                               self.indice_dict if indice_dict is None else indice_dict, _checked=True)
        out.sorted_keys = self.sorted_keys if same else None
        return out

    def replace_feature(self, features: Tensor) -> "SparseConvTensor":
        """The same voxels with other features, e.g. after a BatchNorm or an activation. The result shares this
        tensor's ``indice_dict`` (spconv's contract), so the neighbour maps built so far are reused downstream; see
        :meth:`fresh` for a copy without them."""
        if features.shape[0] != self.features.shape[0]:
            raise ValueError(f"replace_feature: {features.shape[0]} rows for {self.features.shape[0]} voxels")
        return self.derived(features)

    def fresh(self) -> "SparseConvTensor":
        """The same voxels and features (the same tensors, so gradients still flow to them) with a new, empty
        ``indice_dict``: what a second model should be given when the first ran on this tensor with
        ``semantics="spconv1"``. spconv 1.x's convolutions write their neighbour maps into the dictionary they were
        given, which is this tensor's own, and a later convolution with the same ``indice_key`` reuses the stored map
        whatever its own kernel — so model B run on a tensor model A ran on computes on A's maps. (With the default
        ``semantics="spconv2"`` a convolution adds its maps to a copy and the input's dictionary never changes.)"""
        return self.derived(self.features, indice_dict={})

    @property
    def shape(self) -> list[int]:
        """(B, X, Y, Z, C) of the dense grid."""
        return [self.batch_size, *self.spatial_shape, int(self.features.shape[1])]

    def dense(self, channels_first: bool = True) -> Tensor:
        """The dense (B, C, X, Y, Z) grid (``channels_first=False``: (B, X, Y, Z, C)); zero where nothing is
        active. Memory: the whole grid — for checks and small grids."""
        c = self.features.shape[1]
        out = self.features.new_zeros((self.batch_size, *self.spatial_shape, c))
        idx = self.indices.long()
        out[idx[:, 0], idx[:, 1], idx[:, 2], idx[:, 3]] = self.features
        return out.permute(0, 4, 1, 2, 3).contiguous() if channels_first else out

    @classmethod
    def from_dense(cls, dense: Tensor) -> "SparseConvTensor":
        """The active voxels (any feature non-zero) of a dense (B, C, X, Y, Z) grid."""
        if dense.dim() != 5:
            raise ValueError(f"from_dense expects (B, C, X, Y, Z), got {tuple(dense.shape)}")
        channels_last = dense.permute(0, 2, 3, 4, 1)
        active = channels_last.abs().sum(dim=-1) > 0
        indices = active.nonzero().int()
        return cls(channels_last[active], indices, dense.shape[2:], dense.shape[0], _checked=True)

    def __repr__(self) -> str:
        return (f"SparseConvTensor({self.features.shape[0]} voxels x {self.features.shape[1]} channels, "
                f"spatial_shape={self.spatial_shape}, batch_size={self.batch_size})")


def integer(value: Any) -> int | None:
    """``value`` as an int when it is an integer (a Python int, a numpy integer, a 0-d integer tensor), else None (a
    bool, a float, a string, anything else)."""
    if isinstance(value, bool) or (isinstance(value, Tensor) and (value.dim() != 0 or value.dtype == torch.bool)):
        return None
    try:
        return operator.index(value)
    except TypeError:
        return None


def as_int(value: Any, name: str, minimum: int, who: str) -> int:
    """``value`` as an int >= ``minimum``: a ``TypeError`` (not an integer: a bool, a float) or ``ValueError`` (too
    small) naming ``who``, ``name`` and the value otherwise."""
    i = integer(value)
    what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
    if i is None:
        raise TypeError(f"{who}: {name} must be {what}, got {value!r} ({_type_name(value)})")
    if i < minimum:
        raise ValueError(f"{who}: {name} must be {what}, got {i}")
    return i


def _spatial_shape(value: Any) -> tuple[int, int, int]:
    """(X, Y, Z) from three positive integers (a tuple, list, ``torch.Size``, array or 1-d tensor), else a
    ``TypeError``/``ValueError`` naming the value: a float is not truncated, a size <= 0 is refused."""
    what = "SparseConvTensor: spatial_shape must be three positive integers (X, Y, Z)"
    if (integer(value) is not None or isinstance(value, (str, bytes, bool)) or not hasattr(value, "__iter__")
            or (isinstance(value, Tensor) and value.dim() != 1)):
        raise TypeError(f"{what}, got {value!r} ({_type_name(value)})")
    items = list(value)
    if len(items) != 3:
        raise ValueError(f"{what}, got {len(items)} sizes: {value!r}")
    sizes = [integer(v) for v in items]
    for v, i in zip(items, sizes):
        if i is None:
            raise TypeError(f"{what}, got {value!r} ({v!r} is a {_type_name(v)}, not an integer)")
    if min(sizes) < 1:  # type: ignore[type-var]
        raise ValueError(f"{what}, got {value!r}")
    return tuple(sizes)  # type: ignore[return-value]


def _type_name(value: Any) -> str:
    t = type(value)
    return t.__qualname__ if t.__module__ == "builtins" else f"{t.__module__}.{t.__qualname__}"


def _numpy_hint(value: Any, conversion: str) -> str:
    return f" (convert it: {conversion})" if type(value).__module__ == "numpy" else ""


def check_indices(indices: Tensor, shape: tuple[int, ...], batch_size: int) -> tuple[Tensor, Tensor]:
    """Raise a ``ValueError`` naming the first row of (N, 4) ``indices`` outside [0, batch_size) x [0, shape), or
    the first that repeats an earlier row; return the keys' sort (:func:`distilkit.sparse.rulebook.sort_keys`)."""
    if batch_size < 0:
        raise ValueError(f"SparseConvTensor: batch_size must be >= 0, got {batch_size}")
    c = indices.long()
    if c.shape[0]:
        upper = torch.tensor([batch_size, *shape], device=c.device)
        bad = ((c < 0) | (c >= upper)).any(dim=1)
        if bool(bad.any()):
            row = int(bad.nonzero()[0, 0])
            b, x, y, z = c[row].tolist()
            what = (f"batch index {b} outside [0, {batch_size})" if not 0 <= b < batch_size else
                    f"coordinate ({x}, {y}, {z}) outside the grid [0, {shape[0]}) x [0, {shape[1]}) x [0, {shape[2]})")
            raise ValueError(f"SparseConvTensor: indices row {row} = ({b}, {x}, {y}, {z}): {what}")
    sorted_keys, order = sort_keys(c, shape)
    same = sorted_keys[1:] == sorted_keys[:-1]
    if bool(same.any()):
        later, earlier = order[1:][same], order[:-1][same]
        first = int(torch.argmin(later))
        row, before = int(later[first]), int(earlier[first])
        raise ValueError(f"SparseConvTensor: indices row {row} = {tuple(c[row].tolist())} repeats row {before} "
                         "(each voxel must appear once: merge the duplicates' features first)")
    return sorted_keys, order


__all__ = ["SparseConvTensor", "as_int", "check_indices", "integer"]
