"""``distilkit predict``: a trained SSC run predicts a folder's frames in its benchmark's format.

For every frame of the split the run's model (best checkpoint, else last) predicts the voxel classes; a model at a
coarser ``scale`` is upsampled to the 256 x 256 x 32 grid (each voxel repeated ``scale`` times along each axis).

* a SemanticKITTI-format folder (the labelled every-5th frames; for the hidden test split every 5th scan): train ids
  go back to raw ids through the inverse learning map, written as ``<out>/sequences/NN/predictions/NNNNNN.label``
  (uint16, flat) — what ``distilkit eval`` and the benchmark's ``validate_submission.py`` read;
* an SSCBench-KITTI-360 folder (every ``voxels/*.bin`` of the drives; only the inputs are read): train ids 0..18 as
  ``<out>/<drive>/FFFFFF_1_1.npy`` (uint8, 256 x 256 x 32, the format of its ``preprocess/labels``) — what
  ``distilkit eval --classes sscbench-kitti360`` reads.

:func:`prepare_prediction` makes every check and loads the model before a frame is predicted (a command's progress
bar starts after it); :func:`run_prediction` predicts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from distilkit.errors import DistilkitError


def raw_ids(table: Any) -> np.ndarray:
    """(K,) uint16: the raw id each train id of a :class:`~distilkit.data.info.ClassTable` is written with."""
    return np.array([table.learning_map_inv[t] for t in range(table.num_classes)], np.uint16)


FOLDER_DATASETS = ("semantickitti", "semantickitti-ssc", "semantickitti-scan", "semanticposs-ssc",
                   "sscbench-kitti360")


def upsample(labels: np.ndarray, scale: int) -> np.ndarray:
    """(X, Y, Z) labels of a grid ``scale`` times coarser -> the full grid, each voxel repeated ``scale`` times."""
    out = labels
    for axis in range(3):
        out = np.repeat(out, scale, axis=axis)
    return out


@dataclass
class Prediction:
    """A run ready to predict a folder: its model, the frames, and how a frame's train ids are written."""

    model: Any
    dataset: Any
    collate: Callable[[list[Any]], Any]
    scale: int
    write: Callable[[str, np.ndarray], Path]  # (sample id, full-grid train ids) -> the file written
    where: str  # what is written, in words: OUT/sequences/*/predictions/ or OUT/<drive>/FFFFFF_1_1.npy
    sequences: list[str]  # the sequences (SSCBench-KITTI-360: the drives) predicted
    device: torch.device
    run: str
    vote: list[Any] | None = None  # test-time voting: the transforms (distilkit.data.augment) each frame is seen under
    grid: Any = None  # the data's grid (the transforms' centre)


def _validation_line(exc: Exception) -> str:
    """A pydantic error's first message, without its type prefix."""
    errors = getattr(exc, "errors", lambda: [])()
    return str(errors[0].get("msg", exc)).removeprefix("Value error, ") if errors else str(exc)


def prepare_prediction(run: str | Path, dataset_root: str | Path, sequences: Sequence[str] | str, out: str | Path,
                       device: str = "cpu", vote: str | None = None) -> Prediction:
    """Every check ``predict`` makes before a frame is predicted (the run, its data, the folder's frames) and the
    model loaded; ``sequences``: a list, or the name of an official split of the run's dataset (train, valid, test);
    ``vote``: test-time voting over a group of flips and quarter turns (:func:`vote_group`)."""
    from pydantic import ValidationError

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
    name = data.get("dataset")
    if name not in FOLDER_DATASETS:
        raise DistilkitError(f"{run}: trained on {name!r}; predict writes benchmark-format predictions from models "
                             f"trained on a folder ({', '.join(FOLDER_DATASETS)})")
    entry = DATASETS.entry(name)
    what = f"--split {sequences}" if isinstance(sequences, str) else "--sequences"
    given = {k: v for k, v in (data.get("params") or {}).items() if k not in ("val", "val_sequences")}
    try:  # predict reads no validation drive: the run's own is left out
        trained = entry.meta["params"](**given, val=None)
        params = trained.for_submission(str(dataset_root), sequences if isinstance(sequences, str)
                                        else list(sequences))
    except ValidationError as exc:
        raise DistilkitError(f"{what}: {_validation_line(exc)}") from None
    root = Path(out).expanduser()
    if name == "sscbench-kitti360":
        from distilkit.data.sscbench_folder import SscbenchDataset

        dataset: Any = SscbenchDataset(params, "test", what=what, reads="inputs")
        write, where = (lambda sample, labels: _write_train_ids(root, sample, labels)), f"{out}/<drive>/FFFFFF_1_1.npy"
    else:
        from distilkit.data.kitti_folder import SemanticKittiDataset

        dataset = SemanticKittiDataset(params, "test", what=what)
        to_raw = raw_ids(dataset.table)
        write, where = (lambda sample, labels: _write_raw_ids(root, sample, to_raw[labels])), \
            f"{out}/sequences/*/predictions/"
    group = vote_group(vote, run_config(path)) if vote else None
    grid = entry.meta["info"](params).grid
    if group and any(e.turns % 2 for e in group) and grid is not None and grid.shape[0] != grid.shape[1]:
        raise DistilkitError(f"--vote: a quarter turn needs a grid square in x and y; this data's is {grid.shape}")
    model = load_run(path, device=torch.device(device))
    return Prediction(model, dataset, entry.meta["collate"], params.scale, write, where, params.sequences("test"),
                      torch.device(device), str(run), group, grid)


def vote_group(vote: str, config: dict[str, Any]) -> list[Any]:
    """The transforms ``--vote`` names: ``train`` (the group the run trained under, its ``train.augment``) or an
    augmentation written as in a recipe (``{flip: [x, y], rotate90: z}``)."""
    import yaml
    from pydantic import ValidationError

    from distilkit.data.augment import group_of
    from distilkit.recipe.schema import AugmentSpec

    if vote.strip() == "train":
        raw = (config.get("train") or {}).get("augment")
        if not raw:
            raise DistilkitError("--vote train: the run trained without augmentation (its train.augment is not set); "
                                 "name the transforms, e.g. --vote '{flip: [x, y], rotate90: z}'")
    else:
        try:
            raw = yaml.safe_load(vote)
        except yaml.YAMLError as exc:
            raise DistilkitError(f"--vote: not YAML ({exc})") from None
    try:
        spec = AugmentSpec.model_validate(raw)
    except ValidationError as exc:
        raise DistilkitError(f"--vote: {_validation_line(exc)} (e.g. --vote '{{flip: [x, y], rotate90: z}}', or "
                             "--vote train)") from None
    if spec.continuous:
        raise DistilkitError(f"--vote{' train' if vote.strip() == 'train' else ''}: rotate, tilt and scale are "
                             "continuous; voting averages over a finite group of flips and quarter turns (e.g. --vote "
                             "'{flip: [x, y], rotate90: z}')")
    return group_of(spec)


def _write_raw_ids(root: Path, sample: str, raw: np.ndarray) -> Path:
    """SemanticKITTI's submission file of one frame: ``sequences/NN/predictions/NNNNNN.label``, uint16, flat."""
    seq, frame = sample.split("/")
    target = root / "sequences" / seq / "predictions" / f"{frame}.label"
    target.parent.mkdir(parents=True, exist_ok=True)
    raw.astype("<u2").reshape(-1).tofile(target)
    return target


def _write_train_ids(root: Path, sample: str, labels: np.ndarray) -> Path:
    """SSCBench-KITTI-360's prediction of one frame: ``<drive>/FFFFFF_1_1.npy``, uint8 train ids."""
    drive, frame = sample.split("/")
    target = root / drive / f"{frame}_1_1.npy"
    target.parent.mkdir(parents=True, exist_ok=True)
    np.save(target, labels.astype(np.uint8), allow_pickle=False)
    return target


def run_prediction(job: Prediction, progress: Callable[[int, int], None] | None = None) -> int:
    """Predict and write every frame of ``job``; returns how many."""
    model, dataset = job.model, job.dataset
    with torch.no_grad():
        for i in range(len(dataset)):
            scores = _voted(job, dataset[i]) if job.vote else _logits(job, dataset[i])[0]
            job.write(dataset.sample_id(i), upsample(scores.argmax(dim=0).cpu().numpy(), job.scale))
            if progress:
                progress(i + 1, len(dataset))
    return len(dataset)


def _logits(job: Prediction, sample: dict[str, Any]) -> torch.Tensor:
    """(1, K, X, Y, Z) logits of the model's prediction tap for one sample."""
    logits: Any = job.model(job.collate([sample]).to(job.device))[job.model.PREDICTION_TAP]
    if not isinstance(logits, torch.Tensor) or logits.dim() != 5:
        raise DistilkitError(f"{job.run}: its prediction tap {job.model.PREDICTION_TAP!r} is not a voxel grid of "
                             "logits")
    return logits


def _voted(job: Prediction, sample: dict[str, Any]) -> torch.Tensor:
    """(K, X, Y, Z) class probabilities averaged over the frame seen under each transform of the vote, each copy's
    mapped back by the inverse transform (JS3C-Net's voting, its paper's "Joint Learning Protocol")."""
    from distilkit.data.augment import inverse, transform_grid, transform_sample

    total: torch.Tensor | None = None
    for e in job.vote or []:
        probs = _logits(job, transform_sample(sample, e, job.grid))[0].float().softmax(dim=0)
        back = transform_grid(probs.permute(1, 2, 3, 0).cpu().numpy(), inverse(e))  # (X, Y, Z, K), grid axes first
        back_t = torch.from_numpy(back).permute(3, 0, 1, 2)
        total = back_t if total is None else total + back_t
    assert total is not None
    return total / len(job.vote or [1])


def predict_folder(run: str | Path, dataset_root: str | Path, sequences: Sequence[str] | str, out: str | Path,
                   device: str = "cpu", progress: Callable[[int, int], None] | None = None) -> tuple[int, list[str]]:
    """Write the predictions of ``run`` for the frames of ``sequences`` under ``out`` (:func:`prepare_prediction`,
    then :func:`run_prediction`); returns the frame count and the sequences."""
    job = prepare_prediction(run, dataset_root, sequences, out, device)
    return run_prediction(job, progress), job.sequences


__all__ = ["FOLDER_DATASETS", "Prediction", "predict_folder", "prepare_prediction", "raw_ids", "run_prediction",
           "upsample"]
