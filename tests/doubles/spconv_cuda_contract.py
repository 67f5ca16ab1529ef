"""A test double of spconv 2.3.8's CUDA ``indice_conv`` on the CPU: the preconditions its CUDA code enforces, read
from its source, checked on every call, and the product computed with plain PyTorch ops (autograd flows through).

Read in spconv 2.3.8 (``spconv/core.py``, ``spconv/csrc/sparse/convops.py``, ``spconv/pytorch/ops.py``,
``spconv/pytorch/functional.py``):

* GEMM kernels exist for float32 and float16 only; for another dtype the tuner finds none and stops ("can't find
  suitable algorithm"); the filters must have the features' dtype;
* under CUDA autocast ``custom_fwd(cast_inputs=torch.float16)``: both inputs arrive as float16;
* ``indice_pairs`` int32 (2, K, width) — input rows, output rows — with -1 past each offset's count,
  ``indice_pair_num`` int32 (K,);
* filters contiguous in KRSC order (out, K, in);
* an all-zero map that is not submanifold reaches ``TV_ASSERT_RT_ERR(nhot_profile > 0, "this shouldn't happen")``,
  forward and backward (the early return is ``if (subm && all_zero)`` only);
* within one offset no output row twice (the scatter is a plain store per pair in its native algorithm).

Installed for a test by putting this folder first on ``sys.path`` (tests/test_sparse_backends.py's fixture), so
distilkit's dispatch, pair conversion and dtype routing run against it on the CPU.
"""

from __future__ import annotations

import enum

import torch

CALLS: list[dict] = []  # every call's shapes and dtypes, for the tests to read


class ConvAlgo(enum.Enum):
    Native = 0
    MaskImplicitGemm = 1
    MaskSplitImplicitGemm = 2


def _fail(message: str) -> None:
    raise RuntimeError(f"spconv double (CUDA contract): {message}")


def check(features: torch.Tensor, filters: torch.Tensor, pairs: torch.Tensor, counts: torch.Tensor,
          rows_out: int, subm: bool = False) -> None:
    """Raise where spconv's CUDA code would (its message quoted), else return."""
    if features.dtype not in (torch.float32, torch.float16):
        _fail(f"can't find suitable algorithm (features {features.dtype}: kernels for float32 and float16 only)")
    if filters.dtype != features.dtype:
        _fail(f"filters {filters.dtype} against features {features.dtype}")
    if pairs.dtype != torch.int32 or counts.dtype != torch.int32:
        _fail(f"indice pairs {pairs.dtype} and counts {counts.dtype}: both must be int32")
    if pairs.dim() != 3 or pairs.shape[0] != 2:
        _fail(f"indice pairs of shape {tuple(pairs.shape)}, expected (2, K, width)")
    volume = pairs.shape[1]
    if counts.shape != (volume,):
        _fail(f"indice_pair_num of shape {tuple(counts.shape)} for {volume} kernel offsets")
    if not filters.is_contiguous() or filters.dim() != 3 or filters.shape[1] != volume or \
            filters.shape[2] != features.shape[1]:
        _fail(f"filters {tuple(filters.shape)} (contiguous: {filters.is_contiguous()}), expected contiguous KRSC "
              f"(out, {volume}, {features.shape[1]})")
    if not features.is_contiguous():
        _fail("features not contiguous")
    if not isinstance(rows_out, int) or rows_out < 0:
        _fail(f"num_activate_out {rows_out!r}")
    n = counts.tolist()
    if not subm and not any(n):
        _fail("this shouldn't happen (nhot_profile > 0: an all-zero map that is not submanifold)")
    width = pairs.shape[2]
    for k, c in enumerate(n):
        if c < 0 or c > width:
            _fail(f"offset {k}: count {c} outside [0, {width}]")
        inp, out = pairs[0, k], pairs[1, k]
        if bool((inp[c:] != -1).any()) or bool((out[c:] != -1).any()):
            _fail(f"offset {k}: pairs past its count {c} are not -1")
        if c and (int(inp[:c].min()) < 0 or int(inp[:c].max()) >= features.shape[0]):
            _fail(f"offset {k}: input row outside [0, {features.shape[0]})")
        if c and (int(out[:c].min()) < 0 or int(out[:c].max()) >= rows_out):
            _fail(f"offset {k}: output row outside [0, {rows_out})")
        if c and torch.unique(out[:c]).numel() != c:
            _fail(f"offset {k}: an output row twice")


def indice_conv(features: torch.Tensor, filters: torch.Tensor, indice_pairs: torch.Tensor,
                indice_pair_num: torch.Tensor, num_activate_out: int, algo: ConvAlgo = ConvAlgo.Native,
                *args: object, **kwargs: object) -> torch.Tensor:
    """spconv's ``indice_conv`` (non-submanifold), on the CPU under the CUDA contract."""
    if torch.is_autocast_enabled(features.device.type):  # custom_fwd(cast_inputs=torch.float16)
        with torch.autocast(features.device.type, enabled=False):
            return indice_conv(features.half(), filters.half(), indice_pairs, indice_pair_num, num_activate_out,
                               algo)
    check(features, filters, indice_pairs, indice_pair_num, num_activate_out)
    CALLS.append({"dtype": features.dtype, "rows": features.shape[0], "out": num_activate_out,
                  "volume": indice_pairs.shape[1]})
    out = features.new_zeros((num_activate_out, filters.shape[0]))
    for k, c in enumerate(indice_pair_num.tolist()):
        if c:
            rows_in, rows_out = indice_pairs[0, k, :c].long(), indice_pairs[1, k, :c].long()
            out = out.index_add(0, rows_out, features.index_select(0, rows_in) @ filters[:, k, :].t())
    return out
