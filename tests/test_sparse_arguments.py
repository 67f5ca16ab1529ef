"""The sparse layers and ``SparseConvTensor`` check their arguments when built, as ``torch.nn.Conv3d``'s are
checked by ``F.conv3d``: each bad argument a ``TypeError`` (not an integer, not a tensor, not floating) or a
``ValueError`` (out of range) naming the layer, the argument and the value — before, a dilation of 0 summed the
kernel at the centre, a negative one flipped it, a negative padding cropped the grid, a stride of 0 divided by zero,
a float size was truncated. The forms spconv takes (an int, a tuple or a list; numpy integers) still work, with the
same numbers."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d

I32 = torch.int32
ONE = torch.tensor([[0, 1, 2, 3]], dtype=I32)
NONE = torch.zeros(0, 4, dtype=I32)
POS_INT = "must be a positive integer or three of them"
NONNEG_INT = "must be an integer >= 0 or three of them"
SHAPE3 = r"spatial_shape must be three positive integers \(X, Y, Z\)"

# (the call, the exception, a regex of its message)
CASES = [
    # kernel_size
    ("SubMConv3d(3, 4, 0)", ValueError, rf"^SubMConv3d: kernel_size {POS_INT} .*got 0$"),
    ("SubMConv3d(3, 4, -1)", ValueError, rf"^SubMConv3d: kernel_size {POS_INT} .*got -1$"),
    ("SparseConv3d(3, 4, 2.5)", TypeError, rf"^SparseConv3d: kernel_size {POS_INT} .*got 2\.5 \(float\)$"),
    ("SparseConv3d(3, 4, True)", TypeError, rf"^SparseConv3d: kernel_size {POS_INT} .*got True \(bool\)$"),
    ("SparseConv3d(3, 4, '3')", TypeError, r"kernel_size .* got '3' \(str\)$"),
    ("SparseConv3d(3, 4, (3, 3))", ValueError, r"kernel_size .* got 2 values: \(3, 3\)$"),
    ("SparseConv3d(3, 4, (3, 3, 3, 3))", ValueError, r"kernel_size .* got 4 values"),
    ("SparseConv3d(3, 4, (3, 2.5, 3))", TypeError, r"kernel_size .* got \(3, 2\.5, 3\) \(2\.5 is a float, not an "),
    ("SparseConv3d(3, 4, [3, 0, 3])", ValueError, r"kernel_size .* got \[3, 0, 3\]$"),
    ("SparseInverseConv3d(3, 4, 0, indice_key='d')", ValueError, rf"^SparseInverseConv3d: kernel_size {POS_INT}"),
    ("SubMConv3d(3, 4, 2)", ValueError, r"^SubMConv3d\(3 -> 4, kernel \(2, 2, 2\)\): a submanifold convolution "
                                        r"needs an odd kernel .*got kernel_size 2$"),
    ("SubMConv3d(3, 4, (1, 3, 4), name='enc.0')", ValueError, r"^enc\.0: SubMConv3d\(3 -> 4, kernel \(1, 3, 4\)\): "
                                                              r".*odd kernel"),
    # stride, padding, dilation: after the channels and kernel, so the layer is described
    ("SparseConv3d(3, 4, 3, stride=0)", ValueError,
     rf"^SparseConv3d\(3 -> 4, kernel \(3, 3, 3\)\): stride {POS_INT} .*got 0$"),
    ("SparseConv3d(3, 4, 3, stride=(2, 2, -1))", ValueError, r"stride .* got \(2, 2, -1\)$"),
    ("SparseConv3d(3, 4, 3, stride=1.5)", TypeError, r"stride .* got 1\.5 \(float\)$"),
    ("SubMConv3d(3, 4, 3, stride=0)", ValueError, r"^SubMConv3d\(3 -> 4, kernel \(3, 3, 3\)\): stride"),
    ("SparseConv3d(3, 4, 3, padding=-1)", ValueError,
     rf"^SparseConv3d\(3 -> 4, kernel \(3, 3, 3\)\): padding {NONNEG_INT} .*got -1$"),
    ("SparseConv3d(3, 4, 3, padding=(1, -1, 1))", ValueError, r"padding .* got \(1, -1, 1\)$"),
    ("SparseConv3d(3, 4, 3, padding=0.5)", TypeError, r"padding .* got 0\.5 \(float\)$"),
    ("SubMConv3d(3, 4, 3, dilation=0)", ValueError,
     rf"^SubMConv3d\(3 -> 4, kernel \(3, 3, 3\)\): dilation {POS_INT} .*got 0$"),
    ("SubMConv3d(3, 4, 3, dilation=-1)", ValueError, r"dilation .* got -1$"),
    ("SparseConv3d(3, 4, 3, dilation=(1, 0, 1), indice_key='d')", ValueError,
     r"^SparseConv3d\(3 -> 4, kernel \(3, 3, 3\), indice_key='d'\): dilation .* got \(1, 0, 1\)$"),
    # channels
    ("SubMConv3d(0, 4, 3)", ValueError, r"^SubMConv3d: in_channels must be a positive integer, got 0$"),
    ("SparseConv3d(3, 0, 3)", ValueError, r"^SparseConv3d: out_channels must be a positive integer, got 0$"),
    ("SparseConv3d(-3, 4, 3)", ValueError, r"in_channels .* got -3$"),
    ("SubMConv3d(3.0, 4, 3, name='enc')", TypeError, r"^enc: SubMConv3d: in_channels .* got 3\.0 \(float\)$"),
    ("SparseInverseConv3d(3, True, 3, indice_key='d')", TypeError, r"out_channels .* got True \(bool\)$"),
    # the tensor: spatial shape, batch size
    ("SparseConvTensor(torch.zeros(0, 3), NONE, (-3, 8, 8), 1)", ValueError, rf"^SparseConvTensor: {SHAPE3}, got "
                                                                             r"\(-3, 8, 8\)$"),
    ("SparseConvTensor(torch.zeros(0, 3), NONE, (8, 0, 8), 1)", ValueError, r"spatial_shape .* got \(8, 0, 8\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8.7, 8, 8), 1)", TypeError, rf"{SHAPE3}, got \(8\.7, 8, 8\) \(8\.7 is "
                                                                            "a float, not an integer\\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, 8, 1)", TypeError, rf"{SHAPE3}, got 8 \(int\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8), 1)", ValueError, rf"{SHAPE3}, got 2 sizes: \(8, 8\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, '888', 1)", TypeError, rf"{SHAPE3}, got '888' \(str\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8, 8), 1.7)", TypeError,
     r"^SparseConvTensor: batch_size must be an integer >= 0, got 1\.7 \(float\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8, 8), 1.0)", TypeError, r"batch_size .* got 1\.0 \(float\)$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8, 8), True)", TypeError, r"batch_size .* got True \(bool\)$"),
    ("SparseConvTensor(torch.zeros(0, 3), NONE, (8, 8, 8), -1)", ValueError,
     r"^SparseConvTensor: batch_size must be an integer >= 0, got -1$"),
    # the tensor: indices and features
    ("SparseConvTensor(torch.zeros(1, 3), np.array([[0, 1, 2, 3]], np.int32), (8, 8, 8), 1)", TypeError,
     r"^SparseConvTensor: indices must be a torch integer tensor .*got numpy\.ndarray \(convert it: "
     r"torch\.from_numpy\(indices\)\.int\(\)"),
    ("SparseConvTensor(torch.zeros(1, 3), [[0, 1, 2, 3]], (8, 8, 8), 1)", TypeError,
     r"^SparseConvTensor: indices must be a torch integer tensor .*got list$"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE.float(), (8, 8, 8), 1)", TypeError,
     r"^SparseConvTensor: indices must be an int32 \(or int64\) tensor, got torch\.float32$"),
    ("SparseConvTensor(torch.zeros(1, 3, dtype=torch.int64), ONE, (8, 8, 8), 1)", TypeError,
     r"^SparseConvTensor: features must be floating .*got torch\.int64 \(convert them: features\.float\(\)\)$"),
    ("SparseConvTensor(torch.zeros(1, 3, dtype=torch.bool), ONE, (8, 8, 8), 1)", TypeError,
     r"features must be floating .*got torch\.bool"),
    ("SparseConvTensor(np.zeros((1, 3), np.float32), ONE, (8, 8, 8), 1)", TypeError,
     r"features must be a floating torch tensor \(N, C\), got numpy\.ndarray \(convert it: torch\.from_numpy"),
    ("SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8, 8), 1).replace_feature(torch.zeros(1, 3, dtype=torch.int64))",
     TypeError, r"features must be floating .*got torch\.int64"),
]


@pytest.mark.parametrize("call, error, message", CASES, ids=[c[0] for c in CASES])
def test_a_bad_argument_is_refused_by_name(call: str, error: type, message: str) -> None:
    with pytest.raises(error, match=message) as caught:
        eval(call)  # noqa: S307 - the table's own constructor calls
    assert type(caught.value) is error


def test_a_layer_refuses_integer_features_by_their_dtype() -> None:
    """Features made integer after the tensor was built reach the layer's own check: a dtype error, not advice to
    convert the model to int64."""
    x = SparseConvTensor(torch.zeros(1, 3), ONE, (8, 8, 8), 1)
    x.features = x.features.long()
    with pytest.raises(TypeError, match=re.escape("SubMConv3d(3 -> 4, kernel (3, 3, 3)): features must be floating, "
                                                  "got torch.int64 (convert them: features.float())")):
        SubMConv3d(3, 4, 3)(x)


def cloud(shape=(6, 5, 4), n: int = 30) -> SparseConvTensor:
    g = torch.Generator().manual_seed(0)
    idx = torch.unique(torch.stack([torch.randint(0, s, (n,), generator=g) for s in (2, *shape)], 1), dim=0)
    return SparseConvTensor(torch.randn(len(idx), 3, generator=g, dtype=torch.float64), idx.int(), shape, 2)


@pytest.mark.parametrize("kind, spelled, plain", [
    ("subm", dict(kernel_size=[1, 3, 3], padding=(0, 1, 1)), dict(kernel_size=(1, 3, 3), padding=(0, 1, 1))),
    ("subm", dict(kernel_size=np.int64(3), dilation=np.array([1, 2, 1])), dict(kernel_size=3, dilation=(1, 2, 1))),
    ("subm", dict(kernel_size=torch.tensor(3), stride=[1, 1, 1]), dict(kernel_size=3)),
    ("conv", dict(kernel_size=(3, 1, 3), stride=[2, np.int32(2), 1], padding=[1, 0, 1]),
     dict(kernel_size=(3, 1, 3), stride=(2, 2, 1), padding=(1, 0, 1))),
    ("conv", dict(kernel_size=[2, 2, 2], stride=np.int64(2), padding=0, dilation=[1, 1, 1]),
     dict(kernel_size=2, stride=2)),
    ("conv", dict(kernel_size=np.array([3, 3, 3]), dilation=torch.tensor([2, 1, 1])),
     dict(kernel_size=3, dilation=(2, 1, 1))),
])
def test_the_forms_spconv_takes_still_work_with_the_same_numbers(kind: str, spelled: dict, plain: dict) -> None:
    """An int, a tuple, a list, numpy integers (and arrays of them) and 0-d or 1-d integer tensors give the layer
    plain int triples and the same output as the plain spelling; a strided one matches F.conv3d on the dense grid."""
    layer = SubMConv3d if kind == "subm" else SparseConv3d
    torch.manual_seed(0)
    a = layer(np.int64(3), 2, **spelled).double()
    torch.manual_seed(0)
    b = layer(3, 2, **plain).double()
    for name in ("kernel_size", "stride", "padding", "dilation"):
        value = getattr(a, name)
        assert value == getattr(b, name) and all(type(v) is int for v in value), (name, value)
    assert type(a.in_channels) is int
    x = cloud()
    out_a, out_b = a(x), b(x)
    assert torch.equal(out_a.features, out_b.features) and torch.equal(out_a.indices, out_b.indices)
    if kind == "conv":
        want = F.conv3d(x.dense(), a.weight.permute(0, 4, 1, 2, 3), a.bias, stride=a.stride, padding=a.padding,
                        dilation=a.dilation)
        torch.testing.assert_close(out_a.dense(), want * (out_a.dense().abs().sum(1, keepdim=True) > 0))


def test_a_tensor_takes_integer_sizes_in_any_spelling_and_an_empty_batch() -> None:
    """``spatial_shape`` as a list, a tuple, a ``torch.Size``, a numpy array or a 1-d tensor; ``batch_size`` a numpy
    integer or a 0-d tensor; a batch of 0 grids (what ``from_dense`` makes of an empty dense batch, which
    ``torch.nn.Conv3d`` takes too) holds no voxel and convolves to an empty batch."""
    f = torch.zeros(1, 3)
    for shape in ([8, 8, 8], (8, 8, 8), torch.Size([8, 8, 8]), np.array([8, 8, 8]), torch.tensor([8, 8, 8])):
        for batch in (1, np.int64(1), torch.tensor(1)):
            x = SparseConvTensor(f, ONE, shape, batch)
            assert x.spatial_shape == [8, 8, 8] and all(type(s) is int for s in x.spatial_shape)
            assert x.batch_size == 1 and type(x.batch_size) is int
    empty = SparseConvTensor(torch.zeros(0, 3), NONE, (8, 8, 8), 0)
    assert SubMConv3d(3, 2, 3)(empty).dense().shape == (0, 2, 8, 8, 8)
    assert SparseConvTensor.from_dense(torch.zeros(0, 3, 4, 4, 4)).batch_size == 0
    assert torch.nn.Conv3d(3, 2, 3, padding=1)(torch.zeros(0, 3, 8, 8, 8)).shape == (0, 2, 8, 8, 8)
    with pytest.raises(ValueError, match=r"batch index 0 outside \[0, 0\)"):
        SparseConvTensor(f, ONE, (8, 8, 8), 0)
    SparseConvTensor(f.half(), ONE.long(), (8, 8, 8), 1)  # any floating dtype, int64 indices
    SparseConvTensor(f.bfloat16(), ONE, (8, 8, 8), 1)
