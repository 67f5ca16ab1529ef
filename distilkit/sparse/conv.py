"""Sparse 3-D convolution modules with spconv's names, arguments and weight layout, in spconv 2.x's or spconv 1.x's
semantics of ``indice_key``.

``weight`` is (out, k0, k1, k2, in) — spconv 2.2+'s layout (2.1 mostly, 2.0 had (k0, k1, k2, out, in) and 1.x
(k0, k1, k2, in, out): :func:`distilkit.sparse.convert.spconv20_to_spconv2` and ``spconv1_to_spconv2`` convert
those) — and ``bias`` (out,), so a state dict moves between spconv and distilkit unchanged. ``indice_key`` names a
neighbour map kept on the tensor; what a key that already exists means depends on ``semantics``:

* ``"spconv2"`` (the default; spconv 2.x, ``spconv/pytorch/conv.py``): a submanifold convolution reuses the map of
  an earlier one with its key, which must have the same kernel, dilation, grid and number of voxels (else the same
  ``ValueError`` as spconv); a strided convolution whose key exists is an error (spconv asserts); a new map is added
  to the *output's* copy of the dictionary, so it is seen downstream only.
* ``"spconv1"`` (spconv 1.x, ``spconv/conv.py`` and ``indiceConv`` in ``src/spconv/spconv_ops.cc`` at 1.2.1): a
  convolution whose key exists reuses that map *whatever its own kernel*, and the dictionary is shared by every
  tensor of the network. spconv 1.x views the filters as (-1, in, out) and loops over the stored map's offsets only,
  so the stored map's i-th offset multiplies the i-th (in, out) slice of this convolution's kernel flattened in C
  order over (k0, k1, k2): a 3x3x3 kernel on a stored 1x3x3 map uses only its slice ``[:, 0]`` at the 1x3x3
  offsets; the stored map's centre (its middle offset, every site with itself) multiplies the middle slice. A kernel
  with fewer offsets than the stored map is an error (spconv 1.x reads past its filters). spconv 1.x's submanifold
  padding ignores dilation, so a dilated convolution is refused in this mode. Cylinder3D / SCPNet were trained this
  way (one key for the four convolutions of a block).

  The shared dictionary is the *input's*: a convolution writes its map into the ``indice_dict`` of the tensor it
  was given, which is the caller's. So a second model run on a tensor that a first model ran on finds the first
  one's maps under its keys and reuses them (outputs that differ from the second model's on a new tensor, with no
  error), as in spconv 1.x. Give each model its own dictionary: ``model_b(x.fresh())`` (the same voxels and
  features, an empty dictionary; ``x.replace_feature`` keeps the dictionary), or a newly built tensor.

``SparseInverseConv3d(indice_key=K)`` inverts the strided ``SparseConv3d(indice_key=K)`` that produced its input's
ancestors, back onto that convolution's input sites (spconv's decoder pattern). A 1x1x1 convolution (stride 1) is a
matrix product on the features in both versions: no map, no key.

The arguments are checked when a layer is built, as ``torch.nn.Conv3d``'s are by ``F.conv3d``: ``in_channels``
and ``out_channels`` positive integers; ``kernel_size``, ``stride`` and ``dilation`` positive integers and
``padding`` one >= 0, each an integer or three of them (a tuple or list, as spconv takes them); an integer may be a
numpy integer, never a bool or a float. A ``TypeError`` (not an integer) or ``ValueError`` (out of range) names the
layer, the argument and the value; a ``SubMConv3d``'s kernel must be odd. (Unchecked, a dilation of 0 summed every
kernel slice at the centre, a negative one flipped the kernel and a negative padding cropped the grid.)

``indice_key`` must be a ``str`` or None (a ``SparseInverseConv3d``'s a ``str``) and ``bias`` a ``bool`` (or a numpy
bool), else a ``TypeError`` naming the layer and the value. spconv's keywords that are real there but mean nothing
here, as they only choose how spconv computes the same numbers, are accepted and ignored: ``algo`` (its GEMM
algorithm), ``fp32_accum`` (float32 accumulation under half precision: this path's float32 accumulator is always
on), ``large_kernel_fast_algo``, ``record_voxel_count`` (spconv 2.x), ``use_hash`` and ``fused_bn`` (spconv 1.x);
``name`` names the layer in errors. Any other keyword is a ``TypeError`` naming it, as Python's for a function
(``SubMConv3d.__init__() got an unexpected keyword argument 'foo'``).

Pure PyTorch (:mod:`distilkit.sparse.rulebook`, :mod:`distilkit.sparse.function`): no dense grid is allocated,
autograd flows through features and weights, and the CPU results are the same bits in any process.
"""

from __future__ import annotations

import math
from typing import Any, Literal, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from distilkit.sparse.function import rulebook_conv
from distilkit.sparse.rulebook import Rulebook, output_shape, strided, submanifold, triple
from distilkit.sparse.tensor import SparseConvTensor, as_int

Semantics = Literal["spconv1", "spconv2"]
SEMANTICS = ("spconv1", "spconv2")
SPEED_ONLY = frozenset({"algo", "fp32_accum", "large_kernel_fast_algo", "record_voxel_count", "use_hash", "fused_bn"})


def _options(kind: str, options: dict[str, Any]) -> str | None:
    """The layer's ``name`` among spconv's keywords; any keyword that is neither ``name`` nor speed-only is a
    ``TypeError`` naming it, in Python's words."""
    unknown = sorted(set(options) - SPEED_ONLY - {"name"})
    if unknown:
        what = ("an unexpected keyword argument" if len(unknown) == 1 else "unexpected keyword arguments")
        raise TypeError(f"{kind}.__init__() got {what} {', '.join(map(repr, unknown))}")
    name = options.get("name")
    return None if name is None else str(name)


def _key(indice_key: Any, who: str, required: bool) -> str | None:
    """``indice_key`` checked: a str, or None where the layer may have no key (spconv compares keys as strings)."""
    if isinstance(indice_key, str) or (indice_key is None and not required):
        return indice_key
    what = "a str" if required else "a str or None"
    shown = "None" if indice_key is None else f"{indice_key!r} ({type(indice_key).__name__})"
    raise TypeError(f"{who}: indice_key must be {what}, got {shown}")


def _flag(bias: Any, who: str) -> bool:
    """``bias`` checked: a bool (a numpy bool too), never a string or a number whose truth would be taken."""
    if isinstance(bias, (bool, np.bool_)):
        return bool(bias)
    raise TypeError(f"{who}: bias must be a bool, got {bias!r} ({type(bias).__name__})")


class _SparseConvolution(nn.Module):
    """What the three kinds share: the weight (out, k0, k1, k2, in), the bias, spconv's initialisation, the key's
    semantics."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int], stride: int | Sequence[int],
                 padding: int | Sequence[int], dilation: int | Sequence[int], bias: bool,
                 indice_key: str | None, semantics: str, options: dict[str, Any], key_required: bool = False) -> None:
        super().__init__()
        kind = type(self).__name__
        self.layer_name = _options(kind, options)
        if semantics not in SEMANTICS:
            raise ValueError(f"{kind}: semantics must be one of {', '.join(SEMANTICS)}, got {semantics!r}")
        self.semantics = semantics
        who = f"{self.layer_name}: {kind}" if self.layer_name else kind
        self.indice_key = _key(indice_key, who, key_required)
        bias = _flag(bias, who)
        self.in_channels = as_int(in_channels, "in_channels", 1, who)
        self.out_channels = as_int(out_channels, "out_channels", 1, who)
        self.kernel_size = triple(kernel_size, "kernel_size", 1, who)
        who = self.describe()
        self.stride, self.padding = triple(stride, "stride", 1, who), triple(padding, "padding", 0, who)
        self.dilation = triple(dilation, "dilation", 1, who)
        self.weight = nn.Parameter(torch.empty(self.out_channels, *self.kernel_size, self.in_channels))
        self.bias = nn.Parameter(torch.empty(self.out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Kaiming-uniform weights (a = sqrt(5)) and a uniform bias over +-1/sqrt(fan_in), as nn.Conv3d and spconv."""
        fan_in = self.in_channels * math.prod(self.kernel_size)
        bound = math.sqrt(6.0 / ((1 + 5) * fan_in))  # kaiming_uniform_ with a = sqrt(5), gain sqrt(2 / (1 + a^2))
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            b = 1 / math.sqrt(fan_in) if fan_in > 0 else 0.0
            nn.init.uniform_(self.bias, -b, b)

    @property
    def volume(self) -> int:
        return math.prod(self.kernel_size)

    def kernel_matrices(self) -> Tensor:
        """The weight as (K, in, out): one matrix per kernel index in C order."""
        return self.weight.permute(1, 2, 3, 4, 0).reshape(-1, self.in_channels, self.out_channels)

    def describe(self) -> str:
        """How errors name this layer: its name (``name=``, or the model's via :func:`name_modules`) and shape."""
        key = f", indice_key={self.indice_key!r}" if self.indice_key else ""
        what = f"{type(self).__name__}({self.in_channels} -> {self.out_channels}, kernel {self.kernel_size}{key})"
        return f"{self.layer_name}: {what}" if self.layer_name else what

    def _check_input(self, x: SparseConvTensor) -> None:
        if not x.features.is_floating_point():
            raise TypeError(f"{self.describe()}: features must be floating, got {x.features.dtype} (convert them: "
                            "features.float())")
        if x.features.shape[1] != self.in_channels:
            raise ValueError(f"{self.describe()}: {x.features.shape[1]} input channels, expected {self.in_channels}")
        if x.features.dtype != self.weight.dtype and not torch.is_autocast_enabled(x.features.device.type):
            raise ValueError(f"{self.describe()}: {x.features.dtype} features against {self.weight.dtype} weights "
                             f"(convert one: model.to({x.features.dtype}) or features.to({self.weight.dtype}))")

    def _run(self, x: SparseConvTensor, book: Rulebook, rows_out: int) -> Tensor:
        """The convolution on ``book``, with this kernel's first ``book.volume`` slices (all of them unless spconv
        1.x reuses a smaller stored map)."""
        if book.volume > self.volume:
            raise ValueError(f"{self.describe()}: the stored map of indice_key {self.indice_key!r} has "
                             f"{book.volume} kernel offsets, more than this kernel's {self.volume} (spconv 1.x would "
                             "read past the filters)")
        matrices = self.kernel_matrices()
        return rulebook_conv(x.features, matrices if book.volume == self.volume else matrices[:book.volume], book,
                             rows_out, self.bias)

    def _matmul(self, x: SparseConvTensor) -> SparseConvTensor:
        """A 1x1x1 stride-1 convolution, as both spconv versions compute it: a product on the features."""
        weight = self.kernel_matrices()[0]
        if self.bias is None:
            return x.derived(torch.mm(x.features, weight))
        return x.derived(torch.addmm(self.bias, x.features, weight))  # under autocast: autocast's dtype, as a layer

    def _kept(self, x: SparseConvTensor) -> Rulebook | None:
        kept = x.indice_dict.get(self.indice_key) if self.indice_key else None
        return kept if isinstance(kept, Rulebook) else None

    def _store(self, x: SparseConvTensor, book: Rulebook) -> dict[str, Any]:
        """The dictionary the output carries: spconv 1.x shares one and adds to it, spconv 2.x adds to a copy."""
        if not self.indice_key:
            return x.indice_dict
        store = x.indice_dict if self.semantics == "spconv1" else dict(x.indice_dict)
        store[self.indice_key] = book
        return store

    def extra_repr(self) -> str:
        key = f", indice_key={self.indice_key!r}" if self.indice_key else ""
        sem = f", semantics={self.semantics!r}" if self.semantics != "spconv2" else ""
        return (f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, stride={self.stride}, "
                f"padding={self.padding}, dilation={self.dilation}, bias={self.bias is not None}{key}{sem}")


class SubMConv3d(_SparseConvolution):
    """Submanifold convolution: outputs at the input's sites only (odd kernels, e.g. Cylinder3D's 1x3x3, 3x1x3,
    3x3x1 and 3x3x3). ``stride`` and ``padding`` are checked and otherwise ignored, as in spconv.

    With ``semantics="spconv1"`` its map is written into the input tensor's own ``indice_dict`` and reused by any
    later convolution with its key that sees that dictionary — a second model run on the same tensor included; give
    that model ``x.fresh()`` (module docstring)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int] = 3, stride: int = 1,
                 padding: int | Sequence[int] = 0, dilation: int | Sequence[int] = 1, groups: int = 1,
                 bias: bool = True, indice_key: str | None = None, semantics: Semantics = "spconv2",
                 **options: Any) -> None:
        if groups != 1:
            raise ValueError("SubMConv3d: groups other than 1 are not supported")
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key,
                         semantics, options)
        if any(k % 2 == 0 for k in self.kernel_size):
            raise ValueError(f"{self.describe()}: a submanifold convolution needs an odd kernel (centred on each "
                             f"site), got kernel_size {kernel_size!r}")
        if semantics == "spconv1" and self.dilation != (1, 1, 1):
            raise ValueError(f"{self.describe()}: spconv 1.x's submanifold padding ignores dilation "
                             f"{self.dilation}; that convolution is not reproduced (use semantics='spconv2')")

    def rulebook(self, x: SparseConvTensor) -> Rulebook:
        """The neighbour map this convolution runs on (stored under its key on the output; see :meth:`forward`)."""
        return self._map(x)[0]

    def _map(self, x: SparseConvTensor) -> tuple[Rulebook, dict[str, Any]]:
        kept = self._kept(x)
        if kept is None:
            book = submanifold(x.indices, x.spatial_shape, self.kernel_size, self.dilation,
                               x.sorted_keys)
            return book, self._store(x, book)
        if self.semantics == "spconv1":
            if not kept.subm:
                raise ValueError(f"{self.describe()}: indice_key {self.indice_key!r} holds a strided convolution's "
                                 "map; spconv 1.x would run this submanifold convolution on it")
        else:
            self._check_reuse(x, kept)
        if kept.in_indices.shape[0] != x.indices.shape[0]:
            raise ValueError(f"{self.describe()}: subm with same indice_key must have same num of indices, expect "
                             f"{kept.in_indices.shape[0]}, input {x.indices.shape[0]}")
        return kept, x.indice_dict

    def _check_reuse(self, x: SparseConvTensor, kept: Rulebook) -> None:
        """spconv 2.x's checks of a reused key (``_check_subm_reuse_valid``), with its messages."""
        if not kept.subm:
            raise ValueError(f"{self.describe()}: indice_key {self.indice_key!r} holds a strided convolution's map "
                             "(spconv 2.x: only support reuse subm indices)")
        if kept.kernel != self.kernel_size:
            raise ValueError(f"{self.describe()}: subm with same indice_key must have same kernel size, expect "
                             f"{list(kept.kernel)}, this layer {list(self.kernel_size)}")
        if kept.dilation != self.dilation:
            raise ValueError(f"{self.describe()}: subm with same indice_key must have same dilation, expect "
                             f"{list(kept.dilation)}, this layer {list(self.dilation)}")
        if list(kept.in_shape) != list(x.spatial_shape):
            raise ValueError(f"{self.describe()}: subm with same indice_key must have same spatial structure, expect "
                             f"{list(kept.in_shape)}, input {list(x.spatial_shape)}")

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        self._check_input(x)
        if self.volume == 1:
            return self._matmul(x)
        book, store = self._map(x)
        return x.derived(self._run(x, book, x.features.shape[0]), indice_dict=store)


class SparseConv3d(_SparseConvolution):
    """A regular sparse convolution (strided, padded, dilated): active outputs wherever an active input reaches.

    With ``semantics="spconv1"`` its map is written into the input tensor's own ``indice_dict`` (the tensor the
    caller passed), where a second model run on that tensor finds it under the same key; give that model
    ``x.fresh()`` (module docstring)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int] = 3,
                 stride: int | Sequence[int] = 1, padding: int | Sequence[int] = 0, dilation: int | Sequence[int] = 1,
                 groups: int = 1, bias: bool = True, indice_key: str | None = None,
                 semantics: Semantics = "spconv2", **options: Any) -> None:
        if groups != 1:
            raise ValueError("SparseConv3d: groups other than 1 are not supported")
        super().__init__(in_channels, out_channels, kernel_size, stride, padding, dilation, bias, indice_key,
                         semantics, options)

    def _map(self, x: SparseConvTensor) -> tuple[Rulebook, dict[str, Any]]:
        kept = self._kept(x)
        if kept is not None:
            if self.semantics == "spconv2" or kept.subm:
                raise ValueError(f"{self.describe()}: indice_key {self.indice_key!r} already exists in this sparse "
                                 "tensor (spconv 2.x reuses submanifold maps only: give this strided convolution a "
                                 "key of its own)")
            if kept.in_indices.shape[0] != x.indices.shape[0]:
                raise ValueError(f"{self.describe()}: the stored map of indice_key {self.indice_key!r} reads "
                                 f"{kept.in_indices.shape[0]} voxels, the input has {x.indices.shape[0]}")
            return kept, x.indice_dict  # spconv 1.x: the stored map, whatever this kernel
        book = strided(x.indices, x.spatial_shape, self.kernel_size, self.stride, self.padding, self.dilation)
        return book, self._store(x, book)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        self._check_input(x)
        if self.volume == 1 and self.stride == (1, 1, 1) and self.padding == (0, 0, 0):
            return self._matmul(x)
        book, store = self._map(x)
        shape = (book.out_shape if self.semantics == "spconv2" else
                 output_shape(x.spatial_shape, self.kernel_size, self.stride, self.padding, self.dilation))
        out = self._run(x, book, book.out_indices.shape[0])
        return x.derived(out, book.out_indices, shape, store)


class SparseInverseConv3d(_SparseConvolution):
    """The transpose of the ``SparseConv3d`` with the same ``indice_key``: back onto that convolution's input
    sites and grid (conv_transpose3d there). With ``semantics="spconv1"`` the map it inverts is looked up in the
    dictionary shared with the caller's tensor, so it may be one a convolution of another model stored there (module
    docstring: ``x.fresh()``)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int | Sequence[int], indice_key: str,
                 bias: bool = True, semantics: Semantics = "spconv2", **options: Any) -> None:
        super().__init__(in_channels, out_channels, kernel_size, 1, 0, 1, bias, indice_key, semantics, options,
                         key_required=True)

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        self._check_input(x)
        book = self._kept(x)
        if book is None or book.subm:
            raise KeyError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): no strided SparseConv3d with that "
                           f"key ran on this tensor's ancestors (keys: {', '.join(map(str, x.indice_dict)) or 'none'})")
        if self.semantics == "spconv1":
            if book.volume != self.volume:  # spconv 1.x: "inverse conv must have same kernel size as its couple conv"
                raise ValueError(f"{self.describe()}: kernel of {self.volume} offsets, but the convolution it "
                                 f"inverts had {book.volume}")
        else:
            if book.kernel != self.kernel_size:
                raise ValueError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): kernel {self.kernel_size}, "
                                 f"but the convolution it inverts had {book.kernel}")
            if list(x.spatial_shape) != list(book.out_shape):
                raise ValueError(f"{self.describe()}: Inverse with same indice_key must have same spatial structure "
                                 f"(spatial shape), expect {list(book.out_shape)}, input {list(x.spatial_shape)}")
        if x.features.shape[0] != book.out_indices.shape[0]:
            raise ValueError(f"SparseInverseConv3d(indice_key={self.indice_key!r}): {x.features.shape[0]} input "
                             f"voxels, but the convolution it inverts produced {book.out_indices.shape[0]}")
        back = book.inverse()
        out = self._run(x, back, back.out_indices.shape[0])
        return x.derived(out, back.out_indices, back.out_shape)


def name_modules(model: nn.Module, prefix: str = "") -> nn.Module:
    """Give every sparse convolution of ``model`` without a ``name`` its name in the model (``prefix`` first), so
    that errors name the layer as ``model.named_modules()`` does; returns ``model``."""
    for name, module in model.named_modules():
        if isinstance(module, _SparseConvolution) and module.layer_name is None:
            module.layer_name = prefix + name
    return model


def uses_sparse(model: nn.Module) -> bool:
    """Whether ``model`` holds a sparse convolution (whose backend ``DISTILKIT_SPARSE`` chooses)."""
    return any(isinstance(m, _SparseConvolution) for m in model.modules())


__all__ = ["SEMANTICS", "Semantics", "SparseConv3d", "SparseInverseConv3d", "SubMConv3d", "name_modules",
           "uses_sparse"]
