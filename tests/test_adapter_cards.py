"""The built-in adapters (``distilkit_adapters``) are declared by torch-free cards: registering them imports no
torch, each implementation subclasses its card, and each card lists the capabilities (methods of the
implementation) that distillation terms call through their context, so ``validate`` checks them without building
the model."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from distilkit.registry import ADAPTERS, OBJECTIVES, TASK_LOSSES, load_plugins

ROOT = Path(__file__).resolve().parents[1]
CARDS = ["distilkit_adapters.dean.card", "distilkit_adapters.js3cnet.card", "distilkit_adapters.lidiff.card",
         "distilkit_adapters.scpnet.card", "distilkit_adapters.voxformer.card", "distilkit_adapters._cards"]
ADAPTER_NAMES = ["dean-labeler", "js3cnet", "lidiff", "lidiff-refine", "scpnet", "voxformer", "voxformer-proposal"]


def _no_torch(code: str) -> None:
    probe = f"import sys\n{code}\nloaded = sorted(m for m in sys.modules if m.split('.')[0] == 'torch')\n" \
            "assert not loaded, loaded[:5]"
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr


def test_registering_the_builtin_adapters_imports_no_torch() -> None:
    # the registries as registered so far (iterating them would load every plugin and built-in module)
    _no_torch("import distilkit_adapters\ndistilkit_adapters.register()\n"
              "from distilkit.registry import ADAPTERS, TASK_LOSSES\n"
              f"assert sorted(ADAPTERS._entries) == {ADAPTER_NAMES}, sorted(ADAPTERS._entries)\n"
              "assert TASK_LOSSES._entries['lidiff'].impl == 'distilkit_adapters.lidiff.loss:LiDiffLoss'")


@pytest.mark.parametrize("module", CARDS)
def test_a_card_module_imports_no_torch(module: str) -> None:
    _no_torch(f"import {module}")


def _builtin() -> list[tuple[str, Any]]:
    load_plugins()
    return [*((f"adapter:{n}", ADAPTERS.entry(n)) for n in ADAPTER_NAMES),
            ("task_loss:lidiff", TASK_LOSSES.entry("lidiff"))]


@pytest.mark.parametrize("key", [k for k, _ in _builtin()])
def test_the_implementation_subclasses_its_card(key: str) -> None:
    entry = dict(_builtin())[key]
    assert entry.impl.startswith("distilkit_adapters.") and isinstance(entry.card, type)
    assert entry.card.__module__.endswith(".card"), "declared by its torch-free card"
    assert issubclass(entry.obj, entry.card)
    assert entry.obj.Params is entry.card.Params


def _required_capabilities() -> set[str]:
    """Every capability (a method of the teacher's or the student's adapter) a registered term calls."""
    load_plugins()
    out: set[str] = set()
    for entry in [*OBJECTIVES, *TASK_LOSSES]:
        card = entry.card
        out |= set(getattr(card, "REQUIRES", ())) | set(getattr(card, "STUDENT_REQUIRES", ()))
        params = [card.Params()] if _constructible(card.Params) else []
        for p in params:
            out |= set(card.student_requires(p))
        choices = getattr(card.Params, "model_fields", {})
        for field, info in choices.items():  # a capability asked for by one value of a Literal field (vsd's aux_sample)
            for value in getattr(info.annotation, "__args__", ()):
                if isinstance(value, str) and params:
                    try:
                        out |= set(card.student_requires(params[0].model_copy(update={field: value})))
                    except Exception:  # noqa: BLE001 (a value the term refuses: nothing to collect)
                        pass
    return out


def _constructible(params: Any) -> bool:
    try:
        params()
    except Exception:  # noqa: BLE001
        return False
    return True


def test_the_known_capabilities_are_collected() -> None:
    assert {"predict_noise", "generate"} <= _required_capabilities()


@pytest.mark.parametrize("name", ADAPTER_NAMES)
def test_a_card_lists_every_capability_its_implementation_offers_a_term(name: str) -> None:
    """``validate`` reads the card: a capability a term calls and the implementation defines is in CAPABILITIES,
    and CAPABILITIES names only methods of the implementation that some term calls."""
    entry = ADAPTERS.entry(name)
    required = _required_capabilities()
    offered = {cap for cap in required if callable(getattr(entry.obj, cap, None))}
    assert set(entry.card.CAPABILITIES) == offered
    assert all(callable(getattr(entry.obj, cap, None)) for cap in entry.card.CAPABILITIES)


@pytest.mark.parametrize("size", ["tiny", "paper"])
@pytest.mark.parametrize("name", ADAPTER_NAMES)
def test_a_card_declares_whether_its_network_runs_sparse_convolutions(name: str, size: str) -> None:
    """``validate`` reads ``sparse`` from the card (it checks the sparse backend without building the model)."""
    import torch

    from distilkit.data.info import Camera, DataInfo
    from distilkit.sparse import uses_sparse
    from distilkit.structures import VoxelGrid

    entry = ADAPTERS.entry(name)
    eye = tuple(tuple(float(i == j) for j in range(4)) for i in range(4))
    camera = Camera("cam", ((100.0, 0.0, 40.0), (0.0, 100.0, 12.0), (0.0, 0.0, 1.0)), eye, (24, 80))
    info = DataInfo(VoxelGrid(shape=(64, 64, 8), voxel_size=0.8), cameras=(camera,))
    params = entry.card.Params(size=size)
    try:
        with torch.device("meta"):
            model = entry.obj(params, info)
    except RuntimeError:  # a model that computes on real tensors while it is built
        model = entry.obj(params, info)
    assert entry.card.sparse(params) == uses_sparse(model)
