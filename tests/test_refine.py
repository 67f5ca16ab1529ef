"""LiDiff's refinement: the Chamfer training loss against its naive form, and the six-offset point network."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from distilkit.data.batch import Batch
from distilkit.losses.chamfer import chamfer
from distilkit.registry import ADAPTERS, TASK_LOSSES
from distilkit.structures import PointCloud


def naive_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return float(d.min(1).mean() + d.min(0).mean())


def test_chamfer_is_pytorch3ds_squared_form_with_exact_gradients() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(30, 3, generator=g, dtype=torch.float64).requires_grad_()
    b = torch.randn(45, 3, generator=g, dtype=torch.float64).requires_grad_()
    assert float(chamfer(a, b).detach()) == pytest.approx(naive_chamfer(a.detach().numpy(), b.detach().numpy()), rel=1e-12)
    assert torch.autograd.gradcheck(chamfer, (a, b))
    batch_a, batch_b = PointCloud.from_list([a.detach(), a.detach()[:10]]), PointCloud.from_list([b.detach()[:20], b.detach()])
    want = (naive_chamfer(a.detach().numpy(), b.detach().numpy()[:20]) + naive_chamfer(a.detach().numpy()[:10], b.detach().numpy())) / 2
    assert float(chamfer(batch_a, batch_b)) == pytest.approx(want, rel=1e-12)
    with pytest.raises(ValueError, match="empty"):
        chamfer(a[:0], b)
    loss = TASK_LOSSES.get("chamfer")
    term = loss(loss.Params())
    got = term.compute({"student": batch_a, "target": batch_b.points, "target_lengths": batch_b.lengths}, None)
    assert float(got) == pytest.approx(want, rel=1e-12)


def refiner(**kw):
    from distilkit.data.params import SceneParams
    from distilkit.data.scenes import scenes_info

    cls = ADAPTERS.get("lidiff-refine")
    torch.manual_seed(0)
    return cls(cls.Params(**{"channels": 8, **kw}), scenes_info(SceneParams()))


def test_the_refiner_predicts_six_bounded_offsets_per_point_in_any_chunking() -> None:
    m = refiner(max_offset=0.5, train_on="completions")
    coarse = PointCloud.from_list([torch.randn(40, 3) * 5, torch.randn(25, 3) * 5])
    m.train()
    out = m(Batch({"coarse": coarse}, {}, {"size": 2}))["refined"]
    assert out.lengths.tolist() == [240, 150]
    for b in range(2):
        moved = out.cloud(b).view(-1, 6, 3) - coarse.cloud(b)[:, None]
        assert moved.abs().max() <= 0.5 and moved.abs().max() > 0
    m.eval()
    chunked = refiner(max_offset=0.5, chunk=7, train_on="completions").eval()
    chunked.load_state_dict(m.state_dict())
    with torch.no_grad():
        a = m(Batch({"coarse": coarse}, {}, {"size": 2}))["completion"]
        b = chunked(Batch({"coarse": coarse}, {}, {"size": 2}))["completion"]
    assert torch.allclose(a.points, b.points, atol=1e-6)
    assert np.allclose(m.refine_cloud(coarse.cloud(0).numpy()), a.cloud(0).numpy(), atol=1e-6)
    with pytest.raises(TypeError, match="point cloud"):
        m(Batch({"coarse": torch.zeros(2, 3, 3)}, {}, {"size": 2}))


def test_the_refiner_trains_on_jittered_ground_truth_by_default() -> None:
    """LiDiff's refinement training input: the ground truth plus N(0, 0.2^2) per axis clipped at 0.3 m."""
    m = refiner().train()
    scene = torch.randn(2, 50, 3) * 5
    batch = Batch({}, {"scene": scene, "scene_lengths": torch.tensor([50, 30])}, {"size": 2})
    seen = []
    m.refine = lambda coarse: seen.append(coarse) or coarse  # type: ignore[method-assign]
    torch.manual_seed(4)
    m(batch)
    torch.manual_seed(4)
    noise = torch.randn(2, 50, 3) * 0.2
    assert torch.equal(seen[0].points, scene + noise.clamp(-0.3, 0.3)) and seen[0].lengths.tolist() == [50, 30]
    assert float((seen[0].points - scene).abs().max()) <= 0.3 + 1e-6 and bool((noise.abs() > 0.3).any())
    cls = ADAPTERS.get("lidiff-refine")
    assert cls.inputs(cls.Params()) >= {"scene", "coarse"} and cls.inputs(cls.Params(train_on="completions")) == {"coarse"}
    m.eval()  # evaluation refines an auxiliary model's completion, and says so when there is none
    with pytest.raises(ValueError, match="coarse"):
        m(batch)


def test_an_auxiliary_model_marked_training_false_runs_only_in_evaluation() -> None:
    from types import SimpleNamespace

    from distilkit.engine.train.auxiliary import with_aux_inputs

    calls = []

    def model(batch):
        calls.append(1)
        return {"completion": "out"}

    aux = [(SimpleNamespace(training=False, inputs={"completion": "coarse"}), model)]
    batch = Batch({}, {}, {"size": 1})
    assert "coarse" not in with_aux_inputs(batch, aux, training=True).inputs and not calls
    assert with_aux_inputs(batch, aux).inputs["coarse"] == "out" and calls == [1]
