"""``distilkit export RUN --out student.pt``: a trained student's weights alone, for deployment or to start another
recipe from.

``student.pt`` is a plain state dict (parameter name -> tensor), nothing else: no teacher, optimizer, auxiliary
networks or objectives, so ``torch.load(path, weights_only=True)`` reads it and ``model.load_state_dict`` takes it, and
a recipe starts from it with ``init: {checkpoint: student.pt}``. Beside it, ``student.json`` says how to build the
model it fits: the adapter, its parameters, the data it was trained on (dataset and parameters) and the class table
(train id -> name, and the raw ids predictions are written with).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from distilkit.errors import DataError


@dataclass
class Exported:
    weights: Path
    sidecar: Path
    adapter: str
    tensors: int
    step: int


def export_student(run: str | Path, out: str | Path, which: str = "best") -> Exported:
    """Write the student of ``run`` (a stage's run folder or a checkpoint file; ``which`` checkpoint of a folder)
    to ``out`` as a plain state dict, and its description to ``out`` with the suffix ``.json``."""
    import torch

    from distilkit.weights import load_checkpoint
    from distilkit.engine.assemble.runs import _model_of, checkpoint_path, run_config
    from distilkit.files import atomic_torch_save, atomic_write_json

    source = checkpoint_path(run, which)
    ckpt = load_checkpoint(source)
    config = run_config(source)
    model, info = _model_of(source, config)  # the adapter must be installed: the weights are checked against it
    weights = {k: v.detach().cpu().clone() for k, v in ckpt["student"].items()}
    try:  # the shapes alone: built on the meta device, nothing allocated
        with torch.device("meta"):
            own = model.cls(model.params, info).state_dict()
    except Exception:  # an adapter that computes on real tensors while it is built
        own = model.cls(model.params, info).state_dict()
    if set(own) != set(weights) or any(tuple(own[k].shape) != tuple(v.shape) for k, v in weights.items()):
        raise DataError(f"{source}: the student's weights do not fit adapter {model.adapter!r} with the checkpoint's "
                        "parameters (was it written by another version of the adapter?)")
    out = Path(out).expanduser()
    if out.suffix == ".json":
        raise DataError(f"--out {out}: the weights file (e.g. student.pt); its description goes beside it as .json")
    data = config.get("data") or {}
    table = info.classes
    sidecar = out.with_suffix(".json")
    atomic_torch_save(out, weights)
    atomic_write_json(sidecar, {
        "format": "distilkit student weights 1", "weights": out.name, "source": str(source),
        "step": int(ckpt.get("step", 0)), "adapter": model.adapter,
        "adapter_params": model.params.model_dump(mode="json"),
        "data": {"dataset": data.get("dataset"), "params": data.get("params") or {}},
        "classes": {"names": list(table.names), "ignore_index": table.ignore_index,
                    "learning_map_inv": {str(k): v for k, v in table.learning_map_inv.items()}},
        "load": "weights = torch.load(weights, weights_only=True); model.load_state_dict(weights); in a recipe: "
                "init: {checkpoint: <weights>}",
    })
    return Exported(out, sidecar, model.adapter, len(weights), int(ckpt.get("step", 0)))


def build_exported(sidecar: str | Path) -> Any:
    """The adapter an exported ``student.json`` describes, with its weights loaded (``weights_only=True``)."""
    import json

    import torch

    from distilkit.engine.assemble.resolved import ResolvedModel
    from distilkit.engine.assemble.runs import build_model
    from distilkit.registry import ADAPTERS, DATASETS, load_plugins

    sidecar = Path(sidecar)
    meta: dict[str, Any] = json.loads(sidecar.read_text(encoding="utf-8"))
    load_plugins()
    cls = ADAPTERS.get(meta["adapter"])
    entry = DATASETS.entry(meta["data"]["dataset"] or "synthetic-lidar")
    info = entry.meta["info"](entry.meta["params"].model_validate(meta["data"]["params"]))
    model = build_model(ResolvedModel(meta["adapter"], cls, cls.Params.model_validate(meta["adapter_params"])), info)
    model.load_state_dict(torch.load(sidecar.parent / meta["weights"], map_location="cpu", weights_only=True))
    return model.eval()


__all__ = ["Exported", "build_exported", "export_student"]
