"""The sparse backends' dispatch against spconv's CUDA contract, on every CPU run: a test double installed as
``spconv`` and ``spconv_triton`` (tests/doubles/spconv_cuda_contract.py: the preconditions read in spconv 2.3.8's CUDA
code, each shown to fire here) with the CUDA capabilities of :data:`distilkit.sparse.backend.CAPABILITIES` applied to
the CPU — so the pair conversion, the dtype and autocast routing, the empty-map rule and the deterministic rule run
where CI runs; and ``DISTILKIT_SPARSE=bogus`` stopping a run with one line."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest
import torch

from conftest import ROOT
from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d, backend

DOUBLES = Path(__file__).resolve().parent / "doubles"


def _spconv_modules() -> dict:
    return {k: v for k, v in sys.modules.items() if k.split(".")[0] in ("spconv", "spconv_triton",
                                                                          "spconv_cuda_contract")}


@pytest.fixture
def double(monkeypatch: pytest.MonkeyPatch):
    """spconv and spconv-triton replaced by the CUDA-contract double for one test (the real modules put back after),
    the CUDA rows of the capability table applied to the CPU, and ``auto`` offering CPU calls to the libraries."""
    saved = _spconv_modules()
    for name in saved:
        del sys.modules[name]
    monkeypatch.syspath_prepend(str(DOUBLES))
    backend._library.cache_clear()
    real = backend.capability
    monkeypatch.setattr(backend, "capability", lambda name, device: real(name, "cuda"))
    monkeypatch.setattr(backend, "AUTO_DEVICES", ("cuda", "cpu"))
    monkeypatch.delenv(backend.ENV, raising=False)
    import spconv_cuda_contract

    assert spconv_cuda_contract.__file__.startswith(str(DOUBLES))
    spconv_cuda_contract.CALLS.clear()
    try:
        with _deterministic(False):
            yield spconv_cuda_contract
    finally:
        for name in _spconv_modules():
            del sys.modules[name]
        sys.modules.update(saved)
        backend._library.cache_clear()


class _deterministic:
    """PyTorch's deterministic algorithms on or off inside the block (restored after)."""

    def __init__(self, on: bool) -> None:
        self.on = on

    def __enter__(self) -> None:
        self.was = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
        torch.use_deterministic_algorithms(self.on, warn_only=True)

    def __exit__(self, *exc: object) -> None:
        torch.use_deterministic_algorithms(self.was[0], warn_only=self.was[1])


def sites(n: int = 200, size: int = 8, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.unique(torch.randint(0, size, (n, 3), generator=g), dim=0)
    b = torch.randint(0, 2, (len(c), 1), generator=g)
    return torch.cat([b, c], 1).int()


def network(dtype: torch.dtype = torch.float32) -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.ModuleList([SubMConv3d(3, 5, 3, indice_key="a"), SparseConv3d(5, 4, 3, stride=2, padding=1,
                                                                                   indice_key="d"),
                                SparseInverseConv3d(4, 2, 3, indice_key="d")]).to(dtype)


def forward(layers: torch.nn.Module, feats: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    x = SparseConvTensor(feats, idx, (8, 8, 8), 2)
    for layer in layers:
        x = layer(x)
    return x.features


def outputs_and_grads(layers, feats, idx, name: str | None = None):
    feats = feats.clone().requires_grad_(True)
    with backend.record() as ran:
        if name is None:
            out = forward(layers, feats, idx)
        else:
            with backend.using(name):
                out = forward(layers, feats, idx)
    grads = torch.autograd.grad(out.float().square().sum(), [feats, *layers.parameters()])
    return out, grads, ran


def test_each_precondition_of_the_double_fires(double) -> None:
    """The double refuses exactly what spconv's CUDA code refuses, each with its reason."""
    f, w = torch.randn(4, 3), torch.randn(2, 2, 3)
    pairs = torch.tensor([[[0, 1, -1], [2, -1, -1]], [[1, 0, -1], [3, -1, -1]]], dtype=torch.int32)
    counts = torch.tensor([2, 1], dtype=torch.int32)
    good = double.indice_conv(f, w, pairs, counts, 4)
    want = torch.zeros(4, 2)
    want[1] += f[0] @ w[:, 0].t()
    want[0] += f[1] @ w[:, 0].t()
    want[3] += f[2] @ w[:, 1].t()
    torch.testing.assert_close(good, want)
    cases = {
        "can't find suitable algorithm": (f.double(), w.double(), pairs, counts, 4),
        "can't find suitable algorithm ": (f.bfloat16(), w.bfloat16(), pairs, counts, 4),
        "against features": (f, w.half(), pairs, counts, 4),
        "must be int32": (f, w, pairs.long(), counts, 4),
        "must be int32 ": (f, w, pairs, counts.long(), 4),
        "expected (2, K, width)": (f, w, pairs[0], counts, 4),
        "expected contiguous KRSC": (f, w.transpose(0, 2).contiguous().transpose(0, 2), pairs, counts, 4),
        "this shouldn't happen": (f, w, torch.full((2, 2, 1), -1, dtype=torch.int32),
                                  torch.zeros(2, dtype=torch.int32), 4),
        "are not -1": (f, w, torch.where(pairs == -1, torch.zeros_like(pairs), pairs), counts, 4),
        "an output row twice": (f, w, torch.tensor([[[0, 1, -1], [2, -1, -1]], [[1, 1, -1], [3, -1, -1]]],
                                                   dtype=torch.int32), counts, 4),
        "output row outside": (f, w, pairs, counts, 3),
    }
    for reason, args in cases.items():
        with pytest.raises(RuntimeError, match=r"spconv double \(CUDA contract\): .*" + re.escape(reason.strip())):
            double.indice_conv(*args)
    with torch.autocast("cpu", dtype=torch.bfloat16):  # custom_fwd(cast_inputs=torch.float16)
        assert double.indice_conv(f, w, pairs, counts, 4).dtype == torch.float16


@pytest.mark.parametrize("name", ["auto", "spconv", "spconv-triton"])
def test_float32_calls_go_to_the_library_in_its_form_and_agree_with_the_torch_path(double, name) -> None:
    idx = sites()
    feats = torch.randn(len(idx), 3)
    layers = network()
    want, want_grads, ran_torch = outputs_and_grads(layers, feats, idx, "torch")
    got, got_grads, ran = outputs_and_grads(layers, feats, idx, None if name == "auto" else name)
    assert ran_torch == {"torch"}
    assert ran == {"spconv" if name == "auto" else name}, ran
    assert len(double.CALLS) == 3 and all(c["dtype"] == torch.float32 for c in double.CALLS)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    for a, b in zip(got_grads, want_grads):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16])
def test_dtypes_the_libraries_lack_run_on_torch_under_auto_and_are_an_error_when_named(double, dtype) -> None:
    idx = sites()
    layers = network(dtype)
    feats = torch.randn(len(idx), 3, dtype=dtype)
    want, _, _ = outputs_and_grads(layers, feats, idx, "torch")
    got, _, ran = outputs_and_grads(layers, feats, idx)
    assert ran == {"torch"} and not double.CALLS
    assert torch.equal(got, want)
    name = str(dtype).removeprefix("torch.")
    for explicit in ("spconv", "spconv-triton"):
        with backend.using(explicit), pytest.raises(backend.SparseBackendError,
                                                    match=rf"sparse backend {explicit} \(using\(\)\) on the cpu: "
                                                          rf"{name} features: {explicit} computes float32 and "
                                                          rf"float16 only.*DISTILKIT_SPARSE=auto runs such calls on "
                                                          "the torch path"):
            forward(layers, feats, idx)


def test_float16_autocast_goes_to_the_library_bfloat16_autocast_to_torch(double) -> None:
    idx = sites()
    layers = network()
    feats = torch.randn(len(idx), 3)
    with torch.autocast("cpu", dtype=torch.float16), backend.record() as ran:
        half = forward(layers, feats, idx)
    assert ran == {"spconv"} and {c["dtype"] for c in double.CALLS} == {torch.float16}
    double.CALLS.clear()
    with torch.autocast("cpu", dtype=torch.bfloat16), backend.record() as ran:
        forward(layers, feats, idx)
    assert ran == {"torch"} and not double.CALLS
    with torch.autocast("cpu", dtype=torch.bfloat16), backend.using("spconv"), \
            pytest.raises(backend.SparseBackendError, match="bfloat16 autocast on the cpu: it casts autocast's "
                                                            "inputs to float16"):
        forward(layers, feats, idx)


@pytest.mark.parametrize("name", ["auto", "spconv"])
def test_a_map_with_no_pair_never_reaches_the_library(double, name) -> None:
    """An empty sample set: every map is empty. The output is zeros plus the bias (here no rows), the gradients of
    the weights zeros (not None), and the library is never called — also when it is named."""
    layers = network()
    idx = torch.zeros((0, 4), dtype=torch.int32)
    feats = torch.zeros((0, 3), requires_grad=True)
    out, grads, ran = outputs_and_grads(layers, feats, idx, None if name == "auto" else name)
    assert out.shape == (0, 2) and not double.CALLS and ran == set()
    assert all(g is not None and not bool(g.any()) for g in grads)


def test_the_deterministic_settings_keep_auto_on_the_torch_path(double) -> None:
    """spconv tunes its kernel by timing in each process: under the deterministic settings ``auto`` computes on the
    torch path (a fixed order of sums); a named library is honoured."""
    idx = sites()
    layers = network()
    feats = torch.randn(len(idx), 3)
    with _deterministic(True):
        _, _, ran = outputs_and_grads(layers, feats, idx)
        assert ran == {"torch"} and not double.CALLS
        said = backend.describe("cpu")  # validate says why an installed spconv is not used
        assert said.startswith("sparse convolutions on the cpu: the torch path's loop form (DISTILKIT_SPARSE=auto)")
        assert "spconv is installed but the deterministic settings keep auto off it" in said, said
        _, _, ran = outputs_and_grads(layers, feats, idx, "spconv")
        assert ran == {"spconv"} and double.CALLS
    assert backend.describe("cpu").startswith("sparse convolutions on the cpu: spconv (DISTILKIT_SPARSE=auto)")


def test_the_real_modules_come_back_after_the_double() -> None:
    """The fixture puts back whatever spconv was imported before (the CPU build in CI), so the peer tests still
    compare against the real library."""
    backend._library.cache_clear()
    lib = backend._library("spconv")
    if not isinstance(lib, str):
        assert "doubles" not in (sys.modules["spconv"].__file__ or "")


def test_an_unknown_backend_stops_a_run_with_one_line(tmp_path, monkeypatch, capsys) -> None:
    """`distilkit run` with DISTILKIT_SPARSE=bogus (in this process: the variable is read when the run starts):
    exit status 2, one line on stderr, nothing trained."""
    from distilkit.cli import main

    recipe = ROOT / "recipes" / "quickstart.yaml"
    monkeypatch.setenv(backend.ENV, "bogus")
    code = main(["run", str(recipe), "-q", "-o", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 2, out + err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "DISTILKIT_SPARSE='bogus': choose one of auto, torch, spconv, spconv-triton" in \
        lines[0], err
    assert not list(tmp_path.rglob("*.pt"))
