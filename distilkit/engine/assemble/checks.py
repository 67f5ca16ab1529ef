"""What ``distilkit validate`` checks beyond the recipe's own consistency: that a run will find what it needs — the
data (a folder's files, by the dataset's registered ``check``) and every weights file a stage starts from (``teacher:
{checkpoint: ...}``, ``init: {checkpoint: ...}``): that it exists, loads safely and fits the adapter key by key and
shape by shape. The model is built on the meta device and the file is memory-mapped, so nothing large is read."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from distilkit.errors import DataError


def data_problems(res: Any, has_split: Any) -> list[tuple[str, str]]:
    """(field, problem) for each split of the data a run would read that cannot be read (one line each)."""
    from distilkit.registry import DATASETS

    check = DATASETS.entry(res.recipe.data.dataset).meta.get("check")
    if check is None:
        return []
    out = []
    for split in ("train", "val", "test"):
        if has_split(split):
            problem = check(res.data_params, split)
            if problem:
                out.append((f"data.params ({split})", problem))
    return out


def data_notes(res: Any) -> list[str]:
    """What the dataset says of the splits a run would read beside their problems (a dataset's ``notes``: frames
    left out, ...), once each."""
    from distilkit.registry import DATASETS

    notes = DATASETS.entry(res.recipe.data.dataset).meta.get("notes")
    out: list[str] = []
    for split in ("train", "val", "test"):
        if notes is not None and res.has_split(split):
            out += [n for n in notes(res.data_params, split) if n not in out]
    return out


def weights_problems(res: Any) -> list[tuple[str, str]]:
    """(field, problem) for every checkpoint a stage would start from that is missing, unreadable or does not fit."""
    out = []
    for name, stage in res.stages.items():
        spec = stage.spec
        files = []
        if spec.teacher is not None and spec.teacher.checkpoint and stage.teacher is not None:
            files.append(("teacher.checkpoint", spec.teacher.checkpoint, stage.teacher, True, True))
        if spec.init is not None and spec.init.checkpoint:
            files.append(("init.checkpoint", spec.init.checkpoint, stage.student, spec.init.strict, False))
        for field, path, model, strict, whole in files:
            problem = fit_problem(Path(path).expanduser(), model, res.data_info, strict, whole)
            if problem:
                out.append((f"stages.{name}.{field}", problem))
    return out


def model_shapes(model: Any, info: Any) -> dict[str, tuple[int, ...]]:
    """The state dict's shapes of a resolved model, built on the meta device (nothing allocated) where it can be."""
    return {k: tuple(v.shape) for k, v in _built(model, info).state_dict().items()}


def fit_problem(path: Path, model: Any, info: Any, strict: bool, whole: bool = False) -> str | None:
    """None where the weights file at ``path`` loads (read by the adapter's ``read_weights``) and fits ``model``;
    else what is wrong with it. ``whole``: the file must hold the whole model (a teacher's), not a part of it."""
    from distilkit.weights import mismatch, not_a_file, not_finite, spelling, whole_problem

    if not_a_file(path):  # missing, or a folder (what it holds)
        return not_a_file(path)
    try:
        weights = model.cls.read_weights(str(path))
    except DataError as exc:
        return str(exc) if str(path) in str(exc) else f"{path}: {exc}"
    if whole and whole_problem(weights):
        return f"{path}: {whole_problem(weights)}"
    problem = mismatch(model_shapes(model, info), {k: tuple(v.shape) for k, v in weights.items()}, strict,
                       getattr(weights, "scope", ""), spelling(weights))
    if problem:
        return f"{path}: weights do not fit {model.adapter!r}: {problem}"
    bad = not_finite(weights)
    return f"{path}: {bad}" if bad else None




def run_problems(res: Any) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """What a run of ``res`` would meet: (the data's problems, every problem — the data's, the weights files' and
    the sparse convolutions' where they cannot run)."""
    unreadable = data_problems(res, res.has_split)
    return unreadable, unreadable + weights_problems(res) + sparse_problems(res)


def describe(res: Any) -> tuple[str, list[str]]:
    """A resolved recipe in words: its stages (adapter, edges, objectives) on one line, and one line per distinct model
    saying whether it is the paper's network or a stand-in."""
    stages = ", ".join(
        f"{n} ({s.student.adapter}" + "".join(f"; {edge} <- {up}" for edge, up in s.spec.edges().items())
        + ("; teacher <- its own EMA" if s.ema is not None else "")
        + (f"; {', '.join(t.name for t in s.distill)}" if s.distill else "") + ")"
        for n, s in res.stages.items())
    seen: dict[str, list[str]] = {}
    for name, stage in res.stages.items():
        spec = stage.student
        what = spec.card.network(spec.params)
        if what:
            seen.setdefault(f"{spec.adapter}: {what}", []).append(name)
    return stages, [f"model of {', '.join(names)} — {line}" for line, names in seen.items()] + sparse_lines(res)


_SPARSE_MODELS: dict[int, tuple[Any, dict[str, tuple[bool, bool]]]] = {}  # id(res) -> (weakref to res, answer)


def _sparse_models(res: Any) -> dict[str, tuple[bool, bool]]:
    """Per stage: whether its student, and whether a model it only runs forward (its teacher, its auxiliary
    models), hold sparse convolutions (each model built once, on the meta device; the answer kept for the resolved
    recipe while it lives, so validate's problems and its description build each model once)."""
    import weakref

    kept = _SPARSE_MODELS.get(id(res))
    if kept is not None and kept[0]() is res:
        return kept[1]
    answer = _sparse_models_of(res)
    _SPARSE_MODELS[id(res)] = (weakref.ref(res, lambda _, key=id(res): _SPARSE_MODELS.pop(key, None)), answer)
    return answer


def _sparse_models_of(res: Any) -> dict[str, tuple[bool, bool]]:
    sparse: dict[int, bool] = {}

    def uses(spec: Any) -> bool:
        if id(spec) not in sparse:
            declared = getattr(spec.card, "sparse", None)
            answer = declared(spec.params) if declared is not None else None
            if answer is None:  # undeclared (a plug-in's adapter): the model built on the meta device shows it
                from distilkit.sparse import uses_sparse

                answer = uses_sparse(_built(spec, res.data_info))
            sparse[id(spec)] = bool(answer)
        return sparse[id(spec)]

    return {name: (uses(stage.student), any(uses(spec) for spec in ([stage.teacher] if stage.teacher is not None
                                                                    else []) + [a.model for a in stage.aux]))
            for name, stage in res.stages.items()}


def sparse_calls(stage: Any, student: bool, forward: bool) -> list[Any]:
    """The sparse convolutions' calls (:class:`~distilkit.sparse.backend.Call`) a stage makes where it runs, one per
    kind: its student's in a training step (with gradients, in ``train.precision``: bf16/fp16 under autocast) or,
    for a stage that only evaluates, without; its teacher's and auxiliary models' (``forward``) without gradients.
    ``student``/``forward``: which of those hold sparse convolutions."""
    import torch

    from distilkit.engine.assemble.devices import pick_device
    from distilkit.sparse.backend import Call

    train = stage.spec.train
    device = pick_device(train.device).type
    dtype = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}[train.precision]
    autocast = train.precision != "fp32"
    calls = []
    if student:
        calls.append(Call(device, dtype, autocast, gradients=train.steps != 0))
    if forward and not student:  # else the student's call covers it (one refused without gradients is refused with)
        calls.append(Call(device, dtype, autocast, gradients=False))
    return calls


def sparse_problems(res: Any) -> list[tuple[str, str]]:
    """(field, problem) per reason a stage's sparse convolutions cannot run where it will run: the backend
    ``DISTILKIT_SPARSE`` names, asked for the calls of :func:`sparse_calls` (a missing library, spconv's CPU build
    asked for a backward, a dtype it does not compute) — the problem is the line the run stops with, the stages that
    meet it named in the field. A ``DISTILKIT_SPARSE`` that names no backend stops every run."""
    from distilkit.sparse.choice import SparseBackendError, requested

    try:
        requested()
    except SparseBackendError as exc:
        return [("", str(exc))]
    models = _sparse_models(res)
    if not any(student or forward for student, forward in models.values()):
        return []  # no sparse convolution: no backend to ask (and no torch to import)
    from distilkit.sparse import backend

    found: dict[str, list[str]] = {}
    for name, (student, forward) in models.items():
        for call in sparse_calls(res.stages[name], student, forward):
            try:
                backend.choose(call.device, call)
            except backend.SparseBackendError as exc:
                found.setdefault(str(exc), []).append(name)
                break
    return [(f"stage{'s' if len(names) > 1 else ''} {', '.join(names)}", why) for why, names in found.items()]


def sparse_lines(res: Any) -> list[str]:
    """One line per device whose stages build sparse convolutions: which backend computes them there
    (``DISTILKIT_SPARSE``; :mod:`distilkit.sparse.backend`)."""
    models = _sparse_models(res)
    if not any(student or forward for student, forward in models.values()):
        return []
    from distilkit.engine.assemble.devices import pick_device
    from distilkit.sparse import backend

    devices: dict[str, list[str]] = {}
    for name, (student, forward) in models.items():
        if student or forward:
            devices.setdefault(pick_device(res.stages[name].spec.train.device).type, []).append(name)
    return [f"{backend.describe(device)} — stages {', '.join(names)}" for device, names in devices.items()]


def _built(model: Any, info: Any) -> Any:
    """A resolved model built on the meta device (nothing allocated) where it can be."""
    import torch

    from distilkit.engine.assemble.runs import build_model

    try:
        with torch.device("meta"), torch.random.fork_rng(devices=[]):
            return build_model(model, info)
    except Exception:  # an adapter that computes on real tensors while it is built
        with torch.random.fork_rng(devices=[]):
            return build_model(model, info)


__all__ = ["data_notes", "data_problems", "describe", "fit_problem", "model_shapes", "run_problems", "sparse_calls", "sparse_lines",
           "sparse_problems", "weights_problems"]
