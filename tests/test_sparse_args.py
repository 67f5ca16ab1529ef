"""The sparse layers' keywords as spconv's and torch's layers take them: an unknown keyword is a ``TypeError`` naming
it (never said to be "accepted and ignored"), spconv's keywords that only tune its speed are accepted, and
``indice_key`` (a str or None) and ``bias`` (a bool) are checked by type."""

from __future__ import annotations

import re

import numpy as np
import pytest

from distilkit.sparse import SparseConv3d, SparseInverseConv3d, SubMConv3d


@pytest.mark.parametrize("call, message", [
    ("SubMConv3d(3, 4, 3, foo=1)", "SubMConv3d.__init__() got an unexpected keyword argument 'foo'"),
    ("SparseConv3d(3, 4, 3, foo=1, bar=2)", "SparseConv3d.__init__() got unexpected keyword arguments 'bar', 'foo'"),
    ("SparseInverseConv3d(3, 4, 3, indice_key='d', output_padding=1)",
     "SparseInverseConv3d.__init__() got an unexpected keyword argument 'output_padding'"),
    ("SubMConv3d(3, 4, 3, indice_key=5)", "SubMConv3d: indice_key must be a str or None, got 5 (int)"),
    ("SparseConv3d(3, 4, 3, indice_key=('a',), name='down')",
     "down: SparseConv3d: indice_key must be a str or None, got ('a',) (tuple)"),
    ("SparseInverseConv3d(3, 4, 3, indice_key=None)", "SparseInverseConv3d: indice_key must be a str, got None"),
    ("SubMConv3d(3, 4, 3, bias='yes')", "SubMConv3d: bias must be a bool, got 'yes' (str)"),
    ("SparseConv3d(3, 4, 3, bias=1)", "SparseConv3d: bias must be a bool, got 1 (int)"),
])
def test_an_unknown_keyword_or_a_wrong_type_is_a_type_error_naming_it(call: str, message: str) -> None:
    with pytest.raises(TypeError, match=f"^{re.escape(message)}$"):
        eval(call)


def test_spconvs_speed_only_keywords_are_accepted() -> None:
    SubMConv3d(3, 4, 3, algo=None, fp32_accum=None, large_kernel_fast_algo=False, use_hash=False, fused_bn=False,
               name="enc")
    SparseConv3d(3, 4, 3, record_voxel_count=True, bias=np.bool_(False), indice_key="down")
    assert SparseInverseConv3d(3, 4, 3, "down", bias=False).bias is None
