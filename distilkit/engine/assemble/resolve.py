"""Resolve a recipe against the registries: every name, parameter and tap is checked here, before any data is
generated or any model is trained (``distilkit validate``). The result is a
:class:`~distilkit.engine.assemble.resolved.ResolvedRecipe`; a stage's models and terms are resolved by
:mod:`distilkit.engine.assemble.terms`, its metrics, hooks, auxiliary models and labels here."""

from __future__ import annotations

from typing import Any

from distilkit.engine.assemble.resolved import (ResolvedAux, ResolvedHook, ResolvedMetric, ResolvedModel, ResolvedRecipe,
                                             ResolvedStage)
from distilkit.engine.assemble.store_checks import control_problems, store_problems
from distilkit.engine.assemble.terms import (alignment_problems, hook_problems, lookup, param_groups, resolve_model,
                                          resolve_terms, validate_params)
from distilkit.errors import RecipeError
from distilkit.recipe import LossSpec, Recipe, stage_order
from distilkit.registry import DATASETS, HOOKS, METRICS, OBJECTIVES, OPTIMIZERS, SCHEDULES, TASK_LOSSES
from distilkit.taps import kind_fits


def resolve_metric(wanted: str, model: ResolvedModel, info: Any, path: str,
                   problems: list[tuple[str, str]], chosen: bool = True) -> ResolvedMetric | None:
    """``train.metric`` ("KEY" or "METRIC.KEY") among the metrics registered for the kind of the adapter's
    prediction tap whose targets the data provides; the first registered that reports KEY. Not ``chosen`` (the
    recipe left the default): where no such metric reports it, the score that the first metric of the adapter's
    predictions selects by (its ``SELECTS``: LiDiff's point clouds, ``cd``)."""
    tap = model.card.PREDICTION_TAP
    kind = model.card.TAPS.get(tap)
    if kind is None:
        problems.append((f"{path}.model.adapter", f"adapter {model.adapter!r} declares no prediction tap "
                                                  f"(PREDICTION_TAP = {tap!r} is not among its TAPS)"))
        return None
    name, _, key = wanted.rpartition(".")
    fields = info.fields if info is not None else None
    usable = [e for e in METRICS if kind_fits(kind, e.card.SCORES) and (fields is None or not fields or e.card.TARGETS <= fields)]
    for entry in usable:
        if (not name or entry.name == name) and key in entry.card.KEYS:
            return ResolvedMetric(entry.name, entry.card, key)
    own = [e for e in usable if e.card.SELECTS]
    if not chosen and own:
        return ResolvedMetric(own[0].name, own[0].card, own[0].card.SELECTS)
    offered = ", ".join(f"{e.name}.{k}" for e in usable for k in e.card.KEYS) or "none"
    problems.append((f"{path}.train.metric", f"no registered metric scores {kind} predictions (tap {tap!r}) with "
                                             f"{wanted!r} on this data (available: {offered})"))
    return None


def extra_metrics(names: list[str], model: ResolvedModel, info: Any, path: str,
                  problems: list[tuple[str, str]]) -> list[ResolvedMetric]:
    """``train.metrics``: registered metrics that score the adapter's prediction kind on this data."""
    kind = model.card.TAPS.get(model.card.PREDICTION_TAP)
    fields = info.fields if info is not None else None
    out = []
    for i, name in enumerate(names):
        entry = lookup(METRICS, name, f"{path}.train.metrics[{i}]", problems)
        if entry is None or kind is None:
            continue
        if not kind_fits(kind, entry.card.SCORES):
            problems.append((f"{path}.train.metrics[{i}]", f"metric {entry.name!r} scores {entry.card.SCORES} "
                                                          f"predictions; adapter {model.adapter!r} predicts {kind}"))
        elif fields and not entry.card.TARGETS <= fields:
            problems.append((f"{path}.train.metrics[{i}]", f"metric {entry.name!r} reads "
                                                          f"{', '.join(sorted(entry.card.TARGETS - fields))}, which "
                                                          "the data does not provide"))
        else:
            out.append(ResolvedMetric(entry.name, entry.card, entry.card.KEYS[0]))
    return out


def resolve_hooks(specs: list[Any], path: str, problems: list[tuple[str, str]],
                  where: str | None = None) -> list[ResolvedHook]:
    """``train.hooks`` (or the recipe's ``trackers``, ``where``): registered hooks with their parameters, whatever
    each needs installed (its ``check``) and what its parameters need of this machine (its ``ready(params)``: an
    MLflow store's packages or setting, a W&B login), each a one-line problem."""
    out = []
    where = where or f"{path}.train.hooks"
    for i, spec in enumerate(specs):
        entry = lookup(HOOKS, spec.name, f"{where}[{i}].name", problems)
        if entry is None:
            continue
        from distilkit.registry import NoParams

        params = validate_params(entry.meta.get("params", NoParams), spec.params, f"{where}[{i}].params", problems)
        missing = entry.meta.get("check", lambda: None)()
        if missing:
            problems.append((f"{where}[{i}]", missing))
        ready = entry.meta.get("ready")
        unready = ready(params) if ready is not None and params is not None and not missing else None
        if unready:
            problems.append((f"{where}[{i}]", unready))
        if params is not None:
            out.append(ResolvedHook(entry.name, params))
    return out


def resolve_trackers(recipe: Recipe, problems: list[tuple[str, str]]) -> list[ResolvedHook]:
    """The recipe's ``trackers``: registered hooks (``tensorboard``, ``wandb``, ``mlflow``, ``trackio``, a
    plugin's) that every stage runs after its own ``train.hooks``; a tracker's missing library is a problem that
    names its ``pip install`` line, what its store or login needs another (a tracker given twice is refused by the
    recipe's schema)."""
    from distilkit.recipe.schema import HookSpec

    specs = [HookSpec(name=name, params=params) for name, params in recipe.tracker_specs()]
    return resolve_hooks(specs, "", problems, where="trackers")


def resolve_aux(spec: Any, stages: dict[str, ResolvedStage], path: str,
                problems: list[tuple[str, str]]) -> list[ResolvedAux]:
    """The stage's auxiliary models: each upstream stage's model and the inputs its taps become."""
    out = []
    for name, aux in spec.aux.items():
        up = stages.get(aux.from_)
        if up is None:  # an unknown stage is named by stage_order
            continue
        inputs = aux.inputs or {up.student.card.PREDICTION_TAP: name}
        for tap in inputs:
            if tap not in up.student.taps:
                problems.append((f"{path}.aux.{name}.inputs", f"stage {aux.from_!r}'s {up.student.adapter!r} has no tap "
                                                              f"{tap!r} (it has: {', '.join(up.student.taps)})"))
        out.append(ResolvedAux(name, aux.from_, aux.which, up.student, inputs, aux.training))
    return out


def labels_problems(spec: Any, stages: dict[str, ResolvedStage], info: Any, path: str) -> list[tuple[str, str]]:
    """A ``labels`` edge: the upstream stage's predictions can be published, the fields exist; a stage's own
    ``publish``: its predictions can be."""
    from distilkit.taps import publishable

    out = []
    labels = spec.labels
    if labels is not None and labels.from_ in stages:
        up = stages[labels.from_].student
        kind = up.taps.get(up.card.PREDICTION_TAP)
        if not publishable(kind):
            out.append((f"{path}.labels.from", f"stage {labels.from_!r} predicts {kind} ({up.adapter!r}), which cannot "
                                               "be published as labels (voxel_logits and points can)"))
        for key in ("field", "keep"):
            name = getattr(labels, key)
            if name is not None and info is not None and info.fields and name not in info.fields:
                out.append((f"{path}.labels.{key}", f"the data has no field {name!r} (it has: "
                                                    f"{', '.join(sorted(info.fields))})"))
    return out


def data_problems(model: ResolvedModel, info: Any, path: str) -> list[tuple[str, str]]:
    """The inputs the adapter reads that the data does not provide, and parameters it cannot serve."""
    out = []
    missing = sorted(model.card.inputs(model.params) - info.fields) if info.fields else []
    if missing:
        from distilkit.schema_doc import aux_only_inputs

        aux = aux_only_inputs(frozenset(missing))
        hint = (f"; no dataset provides {', '.join(aux)}: a frozen auxiliary model's tap does, e.g. `aux: {{{aux[0]}: "
                f"{{from: STAGE}}}}` (its prediction becomes the input `{aux[0]}`)" if aux else "")
        out.append((f"{path}.adapter", f"adapter {model.adapter!r} reads batch input(s) {', '.join(missing)}, which "
                                       f"the data does not provide (it has: {', '.join(sorted(info.fields))}){hint}"))
    out += [(f"{path}.params.{param}" if param else f"{path}.adapter", problem)
            for param, problem in model.card.check_data(model.params, info)]
    return out


def augment_problems(augment: Any, info: Any, path: str) -> list[tuple[str, str]]:
    """``train.augment`` against the data: quarter turns need a square grid; continuous transforms no grid at all."""
    if augment is None or info.grid is None:
        return []
    if augment.continuous:
        which = ", ".join(k for k in ("rotate", "tilt", "scale") if getattr(augment, k) is not None)
        return [(path, f"{which}: continuous transforms move voxels off the grid, so this data's voxel labels could "
                       "not follow them; use flip and rotate90 (a finite group: voxels onto voxels), or point-cloud "
                       "data (synthetic-scenes)")]
    if augment.rotate90 and info.grid.shape[0] != info.grid.shape[1]:
        return [(f"{path}.rotate90", f"a quarter turn about z needs a grid square in x and y; this data's is "
                                     f"{info.grid.shape}")]
    return []


def _provides(card: Any, capability: str) -> bool:
    """Whether an adapter has the method ``capability``: declared in its card's ``CAPABILITIES`` or defined on it."""
    return capability in getattr(card, "CAPABILITIES", ()) or callable(getattr(card, capability, None))


def resolve(recipe: Recipe, source: str = "recipe") -> ResolvedRecipe:
    """Check everything that can be checked without training; raise :class:`RecipeError` listing all problems."""
    problems: list[tuple[str, str]] = []
    try:
        order = stage_order(recipe)
    except RecipeError as exc:
        problems.extend(exc.problems)
        order = list(recipe.stages)
    ds = lookup(DATASETS, recipe.data.dataset, "data.dataset", problems)
    data_params = validate_params(ds.meta["params"], recipe.data.params, "data.params", problems) if ds else None
    info = ds.meta["info"](data_params) if data_params is not None else None
    stages: dict[str, ResolvedStage] = {}
    trackers = resolve_trackers(recipe, problems)
    for name in order:
        spec = recipe.stages[name]
        path = f"stages.{name}"
        student = resolve_model(spec.model, f"{path}.model", problems)
        aux = resolve_aux(spec, stages, path, problems)
        problems.extend(labels_problems(spec, stages, info, path))
        if student is not None and spec.publish:
            from distilkit.taps import publishable

            kind = student.taps.get(student.card.PREDICTION_TAP)
            if not publishable(kind):
                problems.append((f"{path}.publish", f"{student.adapter!r} predicts {kind}, which cannot be published "
                                                    "(voxel_logits and points can)"))
        stage_info = info
        if info is not None and aux:  # the auxiliary models' inputs are batch fields of this stage
            import dataclasses

            stage_info = dataclasses.replace(info, fields=info.fields | {f for a in aux for f in a.inputs.values()})
        teacher, teacher_from = None, None
        if spec.teacher is not None:
            if spec.teacher.ema is not None:  # the student's moving average: the student's model
                teacher = student
            elif spec.teacher.from_ is not None:
                teacher_from = spec.teacher.from_
                up = stages.get(teacher_from)
                teacher = up.student if up else None
            else:
                assert spec.teacher.model is not None
                teacher = resolve_model(spec.teacher.model, f"{path}.teacher.model", problems)
            if teacher is not None and spec.teacher.taps:  # this stage records more of the teacher
                problems.extend(hook_problems(teacher.adapter, teacher.card, teacher.hooks, spec.teacher.taps,
                                              f"{path}.teacher.taps"))
                teacher = ResolvedModel(teacher.adapter, teacher.card, teacher.params,
                                        {**teacher.hooks, **spec.teacher.taps})
        models = {"student": student, "teacher": teacher}
        task_specs = spec.task_losses
        if task_specs is None and student is not None:
            task_specs = [LossSpec.model_validate(d) for d in student.card.DEFAULT_TASK_LOSSES]
        task = resolve_terms(task_specs or [], TASK_LOSSES, f"{path}.task_losses", models, stage_info, problems)
        distill = resolve_terms(spec.distill, OBJECTIVES, f"{path}.distill", models, stage_info, problems)
        if spec.init is not None and spec.init.from_ is not None and student is not None and spec.init.strict:
            up = stages.get(spec.init.from_)
            if up is not None and (up.student.adapter, up.student.params) != (student.adapter, student.params):
                problems.append((f"{path}.init.from", f"stage {spec.init.from_!r} trains {up.student.adapter!r} with "
                                                      f"other params than this stage's {student.adapter!r}: its "
                                                      "weights may not fit (set `strict: false` to load the ones "
                                                      "that fit by name and shape)"))
        chosen = "metric" in spec.train.model_fields_set  # unset: miou, or the prediction kind's own first score
        metric = resolve_metric(spec.train.metric, student, info, path, problems, chosen) if student is not None \
            else None
        extras = extra_metrics(spec.train.metrics, student, info, path, problems) if student is not None else []
        hooks = resolve_hooks(spec.train.hooks, path, problems)
        hooks += [t for t in trackers if t.name not in {h.name for h in hooks}]  # a stage's own settings win
        if info is not None:
            # a teacher stage was checked as a student, an EMA teacher is the student
            own_teacher = teacher if teacher_from is None and (spec.teacher is None or spec.teacher.ema is None) else None
            for model, where in ((student, f"{path}.model"), (own_teacher, f"{path}.teacher.model")):
                if model is not None:
                    problems.extend(data_problems(model, stage_info, where))
        if info is not None:
            problems.extend(alignment_problems(distill, models, info, f"{path}.distill"))
            problems.extend(augment_problems(spec.train.augment, info, f"{path}.train.augment"))
        problems.extend(store_problems(spec, distill, teacher, info, path) + control_problems(spec, distill, path))
        for i, term in enumerate(distill):  # teacher and student capabilities the objective calls
            for role, model, caps in (("teacher", teacher, term.card.REQUIRES),
                                      ("student", student, term.card.student_requires(term.params))):
                for cap in sorted(caps):
                    if model is not None and not _provides(model.card, cap):
                        problems.append((f"{path}.distill[{i}]", f"{term.name} calls the {role}'s {cap}(), which "
                                                                  f"adapter {model.adapter!r} does not provide"))
        lookup(OPTIMIZERS, spec.optimizer.name, f"{path}.optimizer.name", problems)
        schedule_entry = lookup(SCHEDULES, spec.optimizer.schedule.name, f"{path}.optimizer.schedule.name", problems)
        schedule = None if schedule_entry is None else validate_params(schedule_entry.meta["params"], spec.optimizer.schedule.params,
                                                               f"{path}.optimizer.schedule.params", problems)
        if student is not None:
            groups = param_groups(spec.optimizer.param_groups, task, distill)
            stages[name] = ResolvedStage(name, spec, student, teacher, teacher_from, task, distill, groups, metric,
                                         schedule, [*([metric] if metric else []), *extras], hooks, aux)
    if problems:
        raise RecipeError(problems, source)
    assert data_params is not None
    return ResolvedRecipe(recipe, data_params, info, stages, order)
