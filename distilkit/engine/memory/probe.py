"""A stage's trainer on a small copy of its data, built without any upstream run (the teacher with random weights:
the same tensors, other numbers) — what the memory estimate and the training-step benchmark measure — and the check
``distilkit validate`` makes with it: the stage's first training step on that dry batch, every term (task losses and
distillation objectives) on the shapes its taps will have, where an error is one line naming the stage, the term, the
error and the shapes of what the term read (:class:`StepFailure`)."""

from __future__ import annotations

import contextlib
import dataclasses
import tempfile
from pathlib import Path
from typing import Any, Iterator

from distilkit.errors import DistilkitError


class StepFailure(DistilkitError):
    """A stage's first training step fails on a dry batch, as its run would at step 0: ``field``, the recipe path of
    the term that failed (or of the stage), and ``problem``, what failed, in one line."""

    def __init__(self, field: str, problem: str) -> None:
        self.field, self.problem = field, problem
        super().__init__(f"{field}: {problem}")


class _TermFailed(Exception):
    """Raised through the trainer by a term's ``compute`` (:func:`name_terms`): the term's path and the line."""

    def __init__(self, field: str, problem: str) -> None:
        self.field, self.problem = field, problem
        super().__init__(f"{field}: {problem}")


def probe_trainer(res: Any, stage_name: str, params: Any, run_dir: Path, batch_size: int = 1) -> Any:
    """A :class:`~distilkit.engine.train.trainer.Trainer` of ``stage_name`` on the data ``params`` (e.g. one of its
    dataset's probe plans), at ``batch_size``; it writes nothing (``run_dir`` is kept for callers' files)."""
    import torch

    from distilkit.engine.train.distributed import SINGLE
    from distilkit.engine.train.loader import BatchPlan
    from distilkit.engine.assemble.runs import build_model, freeze
    from distilkit.engine.assemble.devices import pick_device
    from distilkit.engine.train.auxiliary import with_aux_inputs
    from distilkit.engine.train.trainer import Trainer
    from distilkit.registry import DATASETS

    stage = res.stages[stage_name]
    entry = DATASETS.entry(res.recipe.data.dataset)
    info = entry.meta["info"](params)
    train_set = entry.obj(params, "train", None)
    spec = stage.spec.model_copy(update={"train": stage.spec.train.model_copy(update={"batch_size": batch_size})})
    stage = dataclasses.replace(stage, spec=spec)
    device = pick_device(spec.train.device)
    torch.manual_seed(0)
    teacher = None
    if stage.teacher is not None and stage.distill and stage.ema is None:  # an EMA: the trainer's
        teacher = freeze(build_model(stage.teacher, info, "teacher").to(device))
    aux = [(a, freeze(build_model(a.model, info, f"aux model {a.name!r}").to(device))) for a in stage.aux]
    plan = BatchPlan(len(train_set), batch_size, 0, SINGLE)
    trainer = Trainer(stage, info, train_set, plan, device, collate=entry.meta["collate"], teacher=teacher,
                      world=SINGLE, prepare=lambda batch: with_aux_inputs(batch.to(device), aux, training=True))
    if teacher is not None and stage.spec.teacher is not None and stage.spec.teacher.store is not None:
        trainer.store, trainer.teacher = StoredOutputs(trainer), None  # the student never holds the teacher
    return trainer


class StoredOutputs:
    """What a stored stage's trainer reads instead of its teacher, for the memory estimate: the teacher's outputs
    on the probe's first batch, computed once before the steps are measured and copied at each read (as a read
    from the store allocates them), so the teacher's weights and forward are not in the student's figure."""

    def __init__(self, trainer: Any) -> None:
        import torch

        from distilkit.engine.train.precision import autocast

        with torch.no_grad(), autocast(trainer.device, trainer.stage.spec.train.precision):
            self.outputs = trainer.teacher(trainer.first_batch())

    def of(self, batch: Any, device: Any) -> dict[str, Any]:
        import torch

        from distilkit.structures import PointCloud, SparseVoxels

        def copy(v: Any) -> Any:
            if isinstance(v, SparseVoxels):
                return v.with_feats(v.feats.clone())
            if isinstance(v, PointCloud):
                return PointCloud(v.points.clone(), v.lengths)
            return v.clone() if isinstance(v, torch.Tensor) else v
        return {k: copy(v) for k, v in self.outputs.items()}


def describe_value(value: Any) -> str:
    """A tap's value in a few characters: a tensor's shape, a sparse tensor's rows x channels on its grid, a point
    cloud's padded shape."""
    import torch

    if isinstance(value, torch.Tensor):
        return str(tuple(value.shape))
    feats = getattr(value, "feats", None)
    if isinstance(feats, torch.Tensor) and hasattr(value, "spatial_shape"):
        return f"sparse {tuple(feats.shape)} on a {'x'.join(map(str, value.spatial_shape))} grid"
    points = getattr(value, "points", None)
    if isinstance(points, torch.Tensor):
        return f"points {tuple(points.shape)}"
    return type(value).__name__


def name_terms(trainer: Any) -> None:
    """Make every term of ``trainer`` (a probe's: it is thrown away) name itself when its ``compute`` raises: its
    recipe path (``stages.S.distill[i]``, ``stages.S.task_losses[j]``), the error, and what it read (each tap's
    role, name and shape)."""
    from distilkit.engine.train.oom import is_out_of_memory

    stage = trainer.stage
    n_task = len(stage.task_losses)
    n = stage.spec.train.batch_size
    batch_size = f"{n} sample" + ("s" if n != 1 else "")
    for i, term in enumerate(trainer.terms):
        field = f"stages.{stage.name}." + (f"task_losses[{i}]" if i < n_task else f"distill[{i - n_task}]")
        compute = term.module.compute

        def named(taps: dict[str, Any], batch: Any, _compute: Any = compute, _term: Any = term,
                  _field: str = field) -> Any:
            try:
                return _compute(taps, batch)
            except Exception as exc:
                if is_out_of_memory(exc):
                    raise
                read = ", ".join(f"{role} {tap!r} {describe_value(taps[role])}"
                                 for role, tap in _term.spec.taps.items() if role in taps)
                error = str(exc) if isinstance(exc, DistilkitError) else f"{type(exc).__name__}: {exc}"
                raise _TermFailed(_field, f"{_term.what} {_term.spec.name!r} fails on its first step (a dry batch of "
                                          f"{batch_size}): {error}"
                                  + (f" — it read {read}" if read else "")) from exc
        object.__setattr__(term.module, "compute", named)


@contextlib.contextmanager
def first_step(stage_name: str) -> Iterator[None]:
    """Errors of a stage's trainer built on a dry batch and of its first step, as :class:`StepFailure` (a term's
    named by :func:`name_terms`; any other, the stage's); running out of memory passes through (the probe's size is
    not the recipe's)."""
    from distilkit.engine.train.oom import is_out_of_memory

    try:
        yield
    except StepFailure:
        raise
    except _TermFailed as exc:
        raise StepFailure(exc.field, exc.problem) from None
    except Exception as exc:
        if is_out_of_memory(exc):
            raise
        error = str(exc) if isinstance(exc, DistilkitError) else f"{type(exc).__name__}: {exc}"
        raise StepFailure(f"stages.{stage_name}", f"its first training step fails on a dry batch: {error}") from None


def dry_params(res: Any, small: bool = False) -> Any:
    """The data of a dry batch: the dataset's first (smallest) probe, else one scene of the recipe's; ``small``:
    coarser still where the data has a size the probes read (a grid's ``scale`` at least 8 — 32x32x4 voxels —, a
    cloud's ``scene_points``/``scan_points`` at most 4,096/512), so that every term's taps keep their widths and
    their grids' ratios at a fraction of the cost."""
    from distilkit.data.probe import _one_scene
    from distilkit.registry import DATASETS

    probe = DATASETS.entry(res.recipe.data.dataset).meta.get("probe")
    params = probe(res.data_params).probes[0][0] if probe is not None else _one_scene(res.data_params)
    if not small:
        return params
    fields, update = type(params).model_fields, {}
    if "scale" in fields and int(params.scale) < SMALL_SCALE:
        update["scale"] = SMALL_SCALE
    for name, most in (("scene_points", 4096), ("scan_points", 512)):
        if name in fields and int(getattr(params, name)) > most:
            update[name] = most
    return params.model_copy(update=update) if update else params


SMALL_SCALE = 8  # the coarsest grid every shipped network runs at (the tests' two-step runs of the paper recipes)


def _terms_once(res: Any, stage_name: str, params: Any) -> None:
    with tempfile.TemporaryDirectory() as tmp, first_step(stage_name):
        trainer = probe_trainer(res, stage_name, params, Path(tmp))
        name_terms(trainer)
        trainer.student.train()
        trainer.loss_terms(trainer.first_batch())


def check_terms(res: Any, stage_name: str) -> None:
    """Raise :class:`StepFailure` where stage ``stage_name``'s first training step would fail in its terms or its
    models: the trainer built on one sample and every term computed once (the forward and the losses, no backward),
    first on the small data of :func:`dry_params`, and only where that fails again at the probe's size (what fails
    on the small copy alone is the copy's, not the recipe's). A stage that does not train has no terms to run."""
    if res.stages[stage_name].spec.train.steps == 0:
        return
    small, probe = dry_params(res, small=True), dry_params(res)
    try:
        _terms_once(res, stage_name, small)
    except StepFailure:
        if small == probe:
            raise
        _terms_once(res, stage_name, probe)


__all__ = ["SMALL_SCALE", "StoredOutputs", "StepFailure", "check_terms", "describe_value", "dry_params", "first_step", "name_terms",
           "probe_trainer"]
