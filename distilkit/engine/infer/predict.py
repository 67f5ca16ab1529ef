"""``distilkit predict``: a trained SSC run predicts a SemanticKITTI folder's frames in the submission format.

For every frame of the split (the labelled every-5th frames; for the hidden test split every 5th scan), the run's
model (best checkpoint, else last) predicts the voxel classes; a model at a coarser ``scale`` is upsampled to the
256 x 256 x 32 grid (each voxel repeated ``scale`` times along each axis); train ids go back to raw ids through the
inverse learning map, written as ``<out>/sequences/NN/predictions/NNNNNN.label`` (uint16, flat) — what
``distilkit eval`` and the benchmark's ``validate_submission.py`` read.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from distilkit.errors import DistilkitError


def raw_ids(table: Any) -> np.ndarray:
    """(K,) uint16: the raw id each train id of a :class:`~distilkit.data.info.ClassTable` is written with."""
    return np.array([table.learning_map_inv[t] for t in range(table.num_classes)], np.uint16)


FOLDER_DATASETS = ("semantickitti", "semantickitti-ssc", "semantickitti-scan", "semanticposs-ssc")


def upsample(labels: np.ndarray, scale: int) -> np.ndarray:
    """(X, Y, Z) labels of a grid ``scale`` times coarser -> the full grid, each voxel repeated ``scale`` times."""
    out = labels
    for axis in range(3):
        out = np.repeat(out, scale, axis=axis)
    return out


def predict_folder(run: str | Path, dataset_root: str | Path, sequences: Sequence[str] | str, out: str | Path,
                   device: str = "cpu", progress: Callable[[int, int], None] | None = None) -> tuple[int, list[str]]:
    """Write the predictions of ``run`` for the frames of ``sequences`` (a list, or the name of an official split of
    the run's dataset: train, valid, test) under ``out``; returns the frame count and the sequences."""
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.engine.assemble.runs import checkpoint_path, load_run, run_config
    from distilkit.registry import DATASETS

    from distilkit.weights import load_checkpoint

    path = checkpoint_path(Path(run).expanduser(), "any")
    load_checkpoint(path)  # a distilkit checkpoint, or one line saying what it is not
    data = run_config(path).get("data") or {}
    if not data:
        raise DistilkitError(f"{path}: no recipe.resolved.yaml in its run folder, so the data the model was trained "
                             "on is unknown; give predict the stage's run folder (runs/<recipe>/<stage>-<hash>) or "
                             "its checkpoints/best.pt")
    if data.get("dataset") not in FOLDER_DATASETS:
        raise DistilkitError(f"{run}: trained on {data.get('dataset')!r}; predict writes SemanticKITTI-format "
                             f"submissions from models trained on a folder ({', '.join(FOLDER_DATASETS)})")
    entry = DATASETS.entry(data["dataset"])
    trained = entry.meta["params"](**(data.get("params") or {}))
    params = trained.for_submission(str(dataset_root), sequences if isinstance(sequences, str) else list(sequences))
    dataset = SemanticKittiDataset(params, "test", what=f"--split {sequences}" if isinstance(sequences, str)
                                   else "--sequences")
    model = load_run(path, device=torch.device(device))
    collate = entry.meta["collate"]
    to_raw = raw_ids(dataset.table)
    root = Path(out).expanduser()
    with torch.no_grad():
        for i in range(len(dataset)):
            batch = collate([dataset[i]]).to(torch.device(device))
            logits: Any = model(batch)[model.PREDICTION_TAP]
            if not isinstance(logits, torch.Tensor) or logits.dim() != 5:
                raise DistilkitError(f"{run}: its prediction tap {model.PREDICTION_TAP!r} is not a voxel grid of logits")
            labels = upsample(logits[0].argmax(dim=0).cpu().numpy(), params.scale)
            seq, frame = dataset.sample_id(i).split("/")
            target = root / "sequences" / seq / "predictions" / f"{frame}.label"
            target.parent.mkdir(parents=True, exist_ok=True)
            to_raw[labels].astype("<u2").reshape(-1).tofile(target)
            if progress:
                progress(i + 1, len(dataset))
    return len(dataset), params.sequences("test")


__all__ = ["predict_folder", "raw_ids", "upsample"]
