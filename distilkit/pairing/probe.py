"""Each model of the pair run once on a dry batch (the small data of ``validate``'s first step: a 32x32x4 grid, a
few thousand points; widths and grids' ratios kept) for what its card does not say: each tap's channels and shape.
The teacher runs in eval mode, the student in train mode (their modes in a run), both under no_grad, seeded."""

from __future__ import annotations

from typing import Any


def tap_shape(value: Any) -> tuple[int | None, tuple[int, ...] | None]:
    """(channels, spatial shape) of a tap's value: a (B, C, *S) tensor's C and S, a sparse tensor's feature width
    and grid, a point cloud's point width; (None, None) for anything else."""
    import torch

    if isinstance(value, torch.Tensor):
        if value.dim() == 2:  # (N, C) rows: points' or voxels' scores
            return int(value.shape[1]), None
        return (int(value.shape[1]), tuple(int(n) for n in value.shape[2:])) if value.dim() >= 3 else (None, None)
    feats = getattr(value, "feats", None)
    if isinstance(feats, torch.Tensor) and hasattr(value, "spatial_shape"):
        return int(feats.shape[1]), tuple(int(n) for n in value.spatial_shape)
    points = getattr(value, "points", None)
    if isinstance(points, torch.Tensor):
        return int(points.shape[-1]), None
    return None, None


def probe_taps(res: Any, stages: dict[str, str]) -> dict[str, dict[str, tuple[int | None, tuple[int, ...] | None]]]:
    """For each role (-> the stage whose model it is), each tap's (channels, shape) after one forward of the model
    on one sample of the dry batch (with the stage's auxiliary models' inputs)."""
    import torch

    from distilkit.engine.assemble.runs import build_model, freeze
    from distilkit.engine.memory.probe import dry_params
    from distilkit.engine.train.auxiliary import with_aux_inputs
    from distilkit.registry import DATASETS

    params = dry_params(res, small=True)
    entry = DATASETS.entry(res.recipe.data.dataset)
    info = entry.meta["info"](params)
    batch = entry.meta["collate"]([entry.obj(params, "train", None)[0]])
    out = {}
    for role, name in stages.items():
        stage = res.stages[name]
        torch.manual_seed(0)
        with torch.no_grad():
            aux = [(a, freeze(build_model(a.model, info, f"aux model {a.name!r}"))) for a in stage.aux]
            model = build_model(stage.student, info, role).train(role == "student")
            values = model(with_aux_inputs(batch, aux, training=True))
        out[role] = {tap: tap_shape(v) for tap, v in values.items()}
    return out


__all__ = ["probe_taps", "tap_shape"]
