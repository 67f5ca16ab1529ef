"""Sparse backends (``DISTILKIT_SPARSE``): the choice per device and its errors, spconv 2.3.8's computation on
distilkit's maps against the PyTorch path (spconv's CPU build: forward only), spconv's own layers loading distilkit's
state dict, spconv 1.x's reuse of a smaller stored map on spconv, and the stage summary / validate naming the backend.

spconv is a peer library, not a dependency: ``.ci/run`` installs its CPU build (``pip install spconv==2.3.8``) and
sets ``DISTILKIT_REQUIRE_SPCONV=1``, so in CI these tests run; elsewhere they skip where it is missing."""

from __future__ import annotations

import os
import sys

import pytest
import torch

from _no_run_reports import no_run_reports  # noqa: F401  (autouse: nothing here reads a run's report)
from conftest import ROOT
from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d, backend


def spconv_or_skip():
    try:
        import spconv.pytorch as spconv  # noqa: F401
    except Exception as exc:
        if os.environ.get("DISTILKIT_REQUIRE_SPCONV") == "1":
            raise AssertionError(f"DISTILKIT_REQUIRE_SPCONV=1 but spconv does not import: {exc}") from exc
        pytest.skip(f"spconv is not installed ({exc}); .ci/run installs spconv==2.3.8")
    return spconv


def sites(n: int = 300, size: int = 10, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.unique(torch.randint(0, size, (n, 3), generator=g), dim=0)
    b = torch.randint(0, 2, (len(c), 1), generator=g)
    return torch.cat([b, c], 1).int()


def test_the_choice_per_device_and_its_errors(monkeypatch) -> None:
    monkeypatch.delenv(backend.ENV, raising=False)
    assert backend.requested() == "auto" and backend.choose("cpu") == "torch"
    monkeypatch.setenv(backend.ENV, "torch")
    assert backend.choose("cuda") == "torch"
    monkeypatch.setenv(backend.ENV, "cudnn")
    with pytest.raises(backend.SparseBackendError, match=r"DISTILKIT_SPARSE='cudnn': choose one of auto, torch, "
                                                         r"spconv, spconv-triton"):
        backend.choose("cpu")
    monkeypatch.setenv(backend.ENV, "spconv-triton")
    with pytest.raises(backend.SparseBackendError, match=r"sparse backend spconv-triton \(DISTILKIT_SPARSE\) on the "
                                                         r"cpu: spconv_triton does not import|GPUs only"):
        backend.choose("cpu")
    with backend.using("torch"):  # code wins over the variable
        assert backend.choose("cpu") == "torch"
    with pytest.raises(backend.SparseBackendError, match="choose one of"):
        with backend.using("mink"):
            pass


def test_an_explicit_backend_that_does_not_import_is_an_error_never_a_fallback(monkeypatch) -> None:
    """spconv made unimportable in this process (its sys.modules entries None, the backend's cached import probe
    cleared before and after, PyTorch's deterministic algorithms off as in a fresh process): explicit spconv names the
    install, auto on CUDA goes on to the next candidate."""
    for name in {k for k in sys.modules if k.split(".")[0] in backend.LIBRARIES.values()} | {"spconv", "spconv_triton"}:
        monkeypatch.setitem(sys.modules, name, None)
    deterministic = torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled()
    torch.use_deterministic_algorithms(False)
    backend._library.cache_clear()
    try:
        monkeypatch.setenv(backend.ENV, "spconv")
        try:
            out = f"CHOSE {backend.choose('cuda')}\n"
        except backend.SparseBackendError as e:
            out = f"ERR {e}\n"
        monkeypatch.setenv(backend.ENV, "auto")
        out += f"AUTO {backend.choose('cuda')}\n"
    finally:
        backend._library.cache_clear()  # the real modules are back after the test: probed again when next asked
        torch.use_deterministic_algorithms(deterministic[0], warn_only=deterministic[1])
    assert "ERR sparse backend spconv (DISTILKIT_SPARSE) on the cuda: spconv does not import" in out, out
    assert "pip install spconv-cu126" in out and "AUTO torch" in out, out


def network(semantics: str = "spconv2") -> torch.nn.Module:
    """Submanifold, strided and inverse convolutions; with spconv1 the second submanifold layer (3x3x3) reuses the
    first's stored 1x3x3 map (its first 9 kernel slices)."""
    torch.manual_seed(0)
    key = "s" if semantics == "spconv1" else "t"
    return torch.nn.ModuleList([
        SubMConv3d(4, 6, (1, 3, 3), indice_key="s", semantics=semantics),
        SubMConv3d(6, 6, 3, indice_key=key, semantics=semantics),
        SparseConv3d(6, 8, 3, stride=2, padding=1, indice_key="d", semantics=semantics),
        SparseInverseConv3d(8, 5, 3, indice_key="d", semantics=semantics)]).double()


def run(layers: torch.nn.Module, feats: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    x = SparseConvTensor(feats, idx, (10, 10, 10), 2)
    for layer in layers:
        x = layer(x)
    return x.features


@pytest.mark.parametrize("semantics", ["spconv2", "spconv1"])
def test_spconv_computes_the_same_convolutions_on_distilkits_maps(semantics) -> None:
    spconv_or_skip()
    idx = sites()
    feats = torch.randn(len(idx), 4, dtype=torch.float64)
    layers = network(semantics)
    with torch.no_grad(), backend.record() as ran:
        want = run(layers, feats, idx)
        with backend.using("spconv"):
            got = run(layers, feats, idx)
            again = run(layers, feats, idx)
    assert ran == {"torch", "spconv"}
    assert torch.equal(got, again)  # run on one thread: spconv 2.3.8's CPU forward races with more
    assert got.shape == want.shape and got.dtype == torch.float64
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_spconv_on_the_cpu_refuses_a_step_that_needs_gradients_naming_the_way_out() -> None:
    spconv_or_skip()
    idx = sites()
    layers = network()
    with backend.using("spconv"), pytest.raises(backend.SparseBackendError,
                                                match=r"CPU build computes the forward only.*DISTILKIT_SPARSE=torch"):
        run(layers, torch.randn(len(idx), 4, dtype=torch.float64), idx)


def test_spconvs_own_layers_load_distilkits_state_dict_and_agree() -> None:
    """The peer library end to end: spconv.pytorch's SubMConv3d and SparseConv3d with distilkit's weights (the same
    (out, k0, k1, k2, in) layout) on the same tensor give the same features (strided outputs matched by site)."""
    spconv = spconv_or_skip()
    idx = sites()
    feats = torch.randn(len(idx), 4)
    ours = [SubMConv3d(4, 6, 3, indice_key="a"), SparseConv3d(6, 5, 3, stride=2, padding=1)]
    theirs = [spconv.SubMConv3d(4, 6, 3, indice_key="a"), spconv.SparseConv3d(6, 5, 3, stride=2, padding=1)]
    for a, b in zip(ours, theirs):
        b.load_state_dict(a.state_dict())
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # spconv 2.3.8's CPU forward races with more threads (distilkit.sparse.backend)
    try:
        pairs = compare(spconv, ours, theirs, feats, idx)
    finally:
        torch.set_num_threads(threads)
    (i1, f1), (i2, f2) = pairs
    assert torch.equal(i1, i2)
    torch.testing.assert_close(f1, f2, rtol=1e-5, atol=1e-5)


def compare(spconv, ours, theirs, feats, idx):
    """Both networks on the same input: the first layer's outputs row by row, the strided layer's by site."""
    with torch.no_grad():
        x = SparseConvTensor(feats, idx, (10, 10, 10), 2)
        y = spconv.SparseConvTensor(feats, idx, [10, 10, 10], 2)
        x1, y1 = ours[0](x), theirs[0](y)
        assert torch.equal(x1.indices, y1.indices.to(x1.indices.dtype))
        torch.testing.assert_close(x1.features, y1.features, rtol=1e-5, atol=1e-5)
        x2, y2 = ours[1](x1), theirs[1](y1)

    def by_site(t):
        k = ((t.indices[:, 0].long() * 5 + t.indices[:, 1]) * 5 + t.indices[:, 2]) * 5 + t.indices[:, 3]
        order = torch.argsort(k)
        return t.indices[order].long(), t.features[order]

    assert list(x2.spatial_shape) == list(y2.spatial_shape)
    return by_site(x2), by_site(y2)


def test_the_stage_summary_and_validate_name_the_backend(tmp_path, tmp_path_factory, capsys) -> None:
    """A one-step run of a paper network on distilkit.sparse on the synthetic streets: summary.json says torch
    computed its sparse convolutions; validate says which backend each device would use. JS3C-Net's release network
    cut to 2 levels of width 4 (SCPNet's paper network, fixed at its size, took ten times the CPU for the same
    answer). (No validation split: the step and the test scores are the run's sparse convolutions; evaluating the
    same scenes twice more would add nothing.)"""
    import json

    from _camera_kitti import camera_kitti
    from distilkit.cli import main
    from test_paper_recipes import overrides

    path = ROOT / "recipes" / "paper" / "js3cnet.yaml"
    folder = camera_kitti(tmp_path_factory)  # read only
    sets = overrides("js3cnet", folder, small=True) + [
        "data.params.val=null", "stages.*.train.steps=1", "stages.*.train.epochs=null", "stages.*.train.batch_size=1",
        "stages.*.train.device=cpu", "stages.*.model.params.levels=2", "stages.*.model.params.seg_channels=4",
        "stages.*.model.params.ssc_channels=4"]
    assert main(["validate", "--static", str(path), "--set", *sets]) == 0
    out = capsys.readouterr().out
    assert "sparse convolutions on the cpu: the torch path's loop form (DISTILKIT_SPARSE=auto) — stages teacher" in out, out
    assert main(["run", str(path), "-q", "-o", str(tmp_path / "runs"), "--set", *sets, "--stage", "teacher"]) == 0
    summaries = [json.loads(p.read_text()) for p in (tmp_path / "runs").rglob("summary.json")]
    assert summaries and all(s["sparse_backend"] == ["torch"] for s in summaries), summaries
