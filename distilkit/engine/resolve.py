"""Resolve a recipe against the registries: every name, parameter and tap is checked here,
before any data is generated or any model is trained (``distilkit validate``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ValidationError

from distilkit.errors import RecipeError, UnknownNameError
from distilkit.recipe import LossSpec, ModelSpec, ParamGroupSpec, Recipe, pydantic_problems, stage_order
from distilkit.registry import (ADAPTERS, CONNECTORS, DATASETS, HOOKS, METRICS, OBJECTIVES, OPTIMIZERS,
                                RECORDERS, SCHEDULES, TASK_LOSSES, Registry)
from distilkit.taps import TAP_KINDS, kind_fits


@dataclass
class ResolvedTerm:
    name: str
    cls: Any
    params: BaseModel
    weight: float
    taps: dict[str, str]  # role -> tap name (of the student, or of the teacher for a teacher role)
    connector: str | None = None  # projection of the student tap to the teacher's channels
    fields: dict[str, str] = field(default_factory=dict)  # role -> batch field
    key: str = ""  # unique within its list: the name, then name_2, name_3 for repeats (logs, parameter names)
    warmup_steps: int = 0  # the weight grows linearly over the first N steps

    def __post_init__(self) -> None:
        self.key = self.key or self.name


@dataclass
class ResolvedModel:
    adapter: str
    cls: Any
    params: BaseModel
    hooks: dict[str, Any] = field(default_factory=dict)  # recipe taps recorded from submodules

    @property
    def taps(self) -> dict[str, str]:
        """Tap name -> kind: the adapter's declared taps and the recipe's recorded ones."""
        return {**self.cls.TAPS, **{name: h.kind for name, h in self.hooks.items() if name not in self.cls.TAPS}}


@dataclass
class ResolvedMetric:
    """The registered metric that scores a stage's predictions and the score that selects ``best.pt``."""

    name: str
    cls: Any
    key: str

    @property
    def higher_is_better(self) -> bool:
        return self.key not in self.cls.LOWER_IS_BETTER


@dataclass
class ResolvedAux:
    """A frozen auxiliary model: the stage it comes from, its model and the batch inputs its taps become."""

    name: str
    stage: str
    which: str
    model: ResolvedModel
    inputs: dict[str, str]  # its tap -> batch input
    training: bool = True  # also run on training batches (else only in evaluation and publishing)


@dataclass
class ResolvedHook:
    """A registered lifecycle hook and its validated parameters."""

    name: str
    params: BaseModel


@dataclass
class ResolvedStage:
    name: str
    spec: Any
    student: ResolvedModel
    teacher: ResolvedModel | None
    teacher_from: str | None
    task_losses: list[ResolvedTerm] = field(default_factory=list)
    distill: list[ResolvedTerm] = field(default_factory=list)
    param_groups: list[dict[str, Any]] = field(default_factory=list)  # optimizer groups in effect
    metric: ResolvedMetric | None = None
    schedule: BaseModel | None = None  # the learning-rate schedule's validated parameters
    metrics: list[ResolvedMetric] = field(default_factory=list)  # every evaluation's: `metric`'s first, then extras
    hooks: list[ResolvedHook] = field(default_factory=list)  # the recipe's registered hooks (train.hooks)
    aux: list[ResolvedAux] = field(default_factory=list)  # frozen auxiliary models, run before the student


@dataclass
class ResolvedRecipe:
    recipe: Recipe
    data_params: BaseModel
    data_info: Any
    stages: dict[str, ResolvedStage]
    order: list[str]


def _lookup(reg: Registry[Any], name: str, path: str, problems: list[tuple[str, str]]) -> Any:
    try:
        return reg.entry(name)
    except UnknownNameError as exc:
        problems.append((path, str(exc)))
        return None


def _params(model: type[BaseModel], raw: dict[str, Any], path: str, problems: list[tuple[str, str]]) -> BaseModel | None:
    try:
        return model.model_validate(raw)
    except ValidationError as err:
        problems.extend(pydantic_problems(err, path, model=model))
        return None


def _model(spec: ModelSpec, path: str, problems: list[tuple[str, str]]) -> ResolvedModel | None:
    entry = _lookup(ADAPTERS, spec.adapter, f"{path}.adapter", problems)
    if entry is None:
        return None
    params = _params(entry.obj.Params, spec.params, f"{path}.params", problems)
    for name, hook in spec.taps.items():
        if name in entry.obj.TAPS:
            problems.append((f"{path}.taps.{name}", f"adapter {spec.adapter!r} already has a tap {name!r}"))
        if hook.kind not in TAP_KINDS:
            problems.append((f"{path}.taps.{name}.kind", f"unknown tap kind {hook.kind!r} (registered: "
                                                         f"{', '.join(TAP_KINDS)})"))
        recorder = _lookup(RECORDERS, hook.at, f"{path}.taps.{name}.at", problems)
        if recorder is not None and recorder.name == "method" and not hook.method:
            problems.append((f"{path}.taps.{name}.method", "`at: method` needs the method's name"))
    return None if params is None else ResolvedModel(entry.name, entry.obj, params, dict(spec.taps))


def _resolve_fields(term_path: str, cls: Any, given: dict[str, str], info: Any,
                    problems: list[tuple[str, str]]) -> dict[str, str]:
    """The batch field of each batch role: the recipe's choice or the term's default, checked against the data."""
    fields = info.fields if info is not None else frozenset()
    out = {role: given.get(role, cls.default_field(role, fields)) for role in cls.BATCH}
    for role, name in out.items():
        if fields and name not in fields:
            hint = cls.BATCH_HINTS.get(role) if role not in given else None
            problems.append((f"{term_path}.taps.{role}" if role in given else term_path,
                             f"reads batch field {name!r} for its {role!r}, which the data does not provide "
                             f"(it has: {', '.join(sorted(fields))})" + (f"; {hint}" if hint else "")))
    return out


def _resolve_taps(term_path: str, cls: Any, given: dict[str, str], models: dict[str, ResolvedModel | None],
                  problems: list[tuple[str, str]]) -> dict[str, str]:
    """Pick the tap of each role: the recipe's choice (checked) or the model's first tap of that kind."""
    out: dict[str, str] = {}
    for role in given:
        if role not in cls.CONSUMES and role not in cls.BATCH:
            problems.append((f"{term_path}.taps.{role}",
                             f"unknown role (this component takes {sorted([*cls.CONSUMES, *cls.BATCH])})"))
    optional = getattr(cls, "OPTIONAL", frozenset())
    for role, kind in cls.CONSUMES.items():
        model = models.get("teacher" if role in getattr(cls, "TEACHER_ROLES", frozenset()) else "student")
        if model is None or (role in optional and role not in given):
            continue
        taps = model.taps
        if role in given:
            tap = given[role]
            if tap not in taps:
                problems.append((f"{term_path}.taps.{role}",
                                 f"adapter {model.adapter!r} has no tap {tap!r} (it has: {', '.join(taps) or 'none'})"))
            elif not kind_fits(taps[tap], kind):
                problems.append((f"{term_path}.taps.{role}",
                                 f"tap {tap!r} of adapter {model.adapter!r} is {taps[tap]}, but this needs {kind}"))
            else:
                out[role] = tap
        else:
            candidates = [n for n, k in taps.items() if kind_fits(k, kind)]
            if not candidates:
                problems.append((f"{term_path}", f"needs a {kind} tap for the {role}, but adapter {model.adapter!r} "
                                                 f"provides only {', '.join(f'{n} ({k})' for n, k in taps.items()) or 'none'}"))
            else:
                out[role] = candidates[0]
    return out


def _terms(specs: list[LossSpec], reg: Registry[Any], path: str, models: dict[str, ResolvedModel | None],
           info: Any, problems: list[tuple[str, str]]) -> list[ResolvedTerm]:
    out = []
    for i, spec in enumerate(specs):
        p = f"{path}[{i}]"
        entry = _lookup(reg, spec.name, f"{p}.name", problems)
        if entry is None:
            continue
        params = _params(entry.obj.Params, spec.params, f"{p}.params", problems)
        taps = _resolve_taps(p, entry.obj, spec.taps, models, problems)
        fields = _resolve_fields(p, entry.obj, spec.taps, info, problems)
        weight = spec.weight if spec.weight is not None else float(getattr(entry.obj, "DEFAULT_WEIGHT", 1.0))
        connector = getattr(spec, "connector", None) or getattr(entry.obj, "DEFAULT_CONNECTOR", None)
        if connector not in (None, "none"):
            found = _lookup(CONNECTORS, connector, f"{p}.connector", problems)
            connector = found.name if found is not None else connector
        if params is not None:
            if connector not in (None, "none") and not entry.obj.TEACHER_ROLES:
                problems.append((f"{p}.connector", f"{spec.name} reads no teacher tap: there is nothing to project to"))
            seen = sum(t.name == entry.name for t in out)
            out.append(ResolvedTerm(entry.name, entry.obj, params, weight, taps,
                                    None if connector == "none" else connector, fields,
                                    entry.name if not seen else f"{entry.name}_{seen + 1}", spec.warmup_steps))
    return out


def _grid_text(grid: Any) -> str:
    shape = tuple(getattr(grid, "shape", grid))
    size = getattr(grid, "voxel_size", None)
    return f"{shape}" + (f" of {size:g} m voxels" if size is not None else "")


def _camera_text(camera: Any) -> str:
    frames = ", ".join(str(f) for f in camera.frames)
    return f"{camera.name!r} ({camera.size[0]}x{camera.size[1]} pixels, frame{'s' if len(camera.frames) > 1 else ''} {frames})"


def alignment_problems(terms: list[ResolvedTerm], models: dict[str, ResolvedModel | None], info: Any,
                       path: str) -> list[tuple[str, str]]:
    """Student/teacher tap pairs that cannot be aligned, known from the adapters' declarations: sparse
    features must lie on grids of one volume that differ by integer factors per axis, voxel logits must
    share the grid, image features must come from the same camera."""
    from distilkit.geometry.voxel import grid_factors

    out = []
    s_model, t_model = models.get("student"), models.get("teacher")
    if s_model is None or t_model is None:
        return out
    for i, term in enumerate(terms):
        for role, tap in term.taps.items():
            # a teacher role pairs with the student role of the same suffix (teacher_logits: student_logits)
            partner = "student" + role[len("teacher"):] if role in term.cls.TEACHER_ROLES else None
            if partner not in term.taps:
                continue
            s_tap = term.taps[partner]
            where = f"{term.name}: student tap {s_tap!r} ({s_model.adapter}) and teacher tap {tap!r} ({t_model.adapter})"
            s_cam = s_model.cls.tap_camera(s_tap, s_model.params, info)
            t_cam = t_model.cls.tap_camera(tap, t_model.params, info)
            if s_cam is not None and t_cam is not None and s_cam != t_cam:
                out.append((f"{path}[{i}]", f"{where} see through cameras {_camera_text(s_cam)} and "
                                            f"{_camera_text(t_cam)}: image features of different cameras (or frames) "
                                            "cannot be compared pixel by pixel"))
            s_grid = s_model.cls.tap_grid(s_tap, s_model.params, info)
            t_grid = t_model.cls.tap_grid(tap, t_model.params, info)
            if s_grid is None or t_grid is None:
                continue
            kind = term.cls.CONSUMES[role]
            how = grid_factors(s_grid, t_grid)
            if isinstance(how, str) or (kind == "voxel_logits" and how[0] != "same"):
                why = how if isinstance(how, str) else f"{kind} must share one grid"
                out.append((f"{path}[{i}]", f"{where} on grids {_grid_text(s_grid)} and {_grid_text(t_grid)} cannot "
                                            f"be aligned: {why}"))
    return out


def param_groups(given: list[Any] | None, task: list[ResolvedTerm], distill: list[ResolvedTerm]) -> list[dict[str, Any]]:
    """The optimizer's parameter groups: the recipe's, or else those the stage's terms ask for."""
    if given is not None:
        return [g.model_dump() for g in given]
    out = []
    for prefix, terms in (("task", task), ("distill", distill)):
        for t in terms:
            for g in getattr(t.cls, "DEFAULT_PARAM_GROUPS", []):
                out.append(ParamGroupSpec.model_validate({**g, "match": f"{prefix}.{t.key}.{g['match']}"}).model_dump())
    return out


def resolve_metric(wanted: str, model: ResolvedModel, info: Any, path: str,
                   problems: list[tuple[str, str]], chosen: bool = True) -> ResolvedMetric | None:
    """``train.metric`` ("KEY" or "METRIC.KEY") among the metrics registered for the kind of the adapter's
    prediction tap whose targets the data provides; the first registered that reports KEY. Not ``chosen`` (the
    recipe left the default): where no such metric reports it, the score that the first metric of the adapter's
    predictions selects by (its ``SELECTS``: LiDiff's point clouds, ``cd``)."""
    tap = model.cls.PREDICTION_TAP
    kind = model.cls.TAPS.get(tap)
    if kind is None:
        problems.append((f"{path}.model.adapter", f"adapter {model.adapter!r} declares no prediction tap "
                                                  f"(PREDICTION_TAP = {tap!r} is not among its TAPS)"))
        return None
    name, _, key = wanted.rpartition(".")
    fields = info.fields if info is not None else None
    usable = [e for e in METRICS if kind_fits(kind, e.obj.SCORES) and (fields is None or not fields or e.obj.TARGETS <= fields)]
    for entry in usable:
        if (not name or entry.name == name) and key in entry.obj.KEYS:
            return ResolvedMetric(entry.name, entry.obj, key)
    own = [e for e in usable if e.obj.SELECTS]
    if not chosen and own:
        return ResolvedMetric(own[0].name, own[0].obj, own[0].obj.SELECTS)
    offered = ", ".join(f"{e.name}.{k}" for e in usable for k in e.obj.KEYS) or "none"
    problems.append((f"{path}.train.metric", f"no registered metric scores {kind} predictions (tap {tap!r}) with "
                                             f"{wanted!r} on this data (available: {offered})"))
    return None


def extra_metrics(names: list[str], model: ResolvedModel, info: Any, path: str,
                  problems: list[tuple[str, str]]) -> list[ResolvedMetric]:
    """``train.metrics``: registered metrics that score the adapter's prediction kind on this data."""
    kind = model.cls.TAPS.get(model.cls.PREDICTION_TAP)
    fields = info.fields if info is not None else None
    out = []
    for i, name in enumerate(names):
        entry = _lookup(METRICS, name, f"{path}.train.metrics[{i}]", problems)
        if entry is None or kind is None:
            continue
        if not kind_fits(kind, entry.obj.SCORES):
            problems.append((f"{path}.train.metrics[{i}]", f"metric {entry.name!r} scores {entry.obj.SCORES} "
                                                          f"predictions; adapter {model.adapter!r} predicts {kind}"))
        elif fields and not entry.obj.TARGETS <= fields:
            problems.append((f"{path}.train.metrics[{i}]", f"metric {entry.name!r} reads "
                                                          f"{', '.join(sorted(entry.obj.TARGETS - fields))}, which "
                                                          "the data does not provide"))
        else:
            out.append(ResolvedMetric(entry.name, entry.obj, entry.obj.KEYS[0]))
    return out


def resolve_hooks(specs: list[Any], path: str, problems: list[tuple[str, str]]) -> list[ResolvedHook]:
    """``train.hooks``: registered hooks with their parameters, and whatever each needs installed."""
    out = []
    for i, spec in enumerate(specs):
        entry = _lookup(HOOKS, spec.name, f"{path}.train.hooks[{i}].name", problems)
        if entry is None:
            continue
        from distilkit.registry import NoParams

        params = _params(entry.meta.get("params", NoParams), spec.params, f"{path}.train.hooks[{i}].params", problems)
        missing = entry.meta.get("check", lambda: None)()
        if missing:
            problems.append((f"{path}.train.hooks[{i}]", missing))
        if params is not None:
            out.append(ResolvedHook(entry.name, params))
    return out


def resolve_aux(spec: Any, stages: dict[str, ResolvedStage], path: str,
                problems: list[tuple[str, str]]) -> list[ResolvedAux]:
    """The stage's auxiliary models: each upstream stage's model and the inputs its taps become."""
    out = []
    for name, aux in spec.aux.items():
        up = stages.get(aux.from_)
        if up is None:  # an unknown stage is named by stage_order
            continue
        inputs = aux.inputs or {up.student.cls.PREDICTION_TAP: name}
        for tap in inputs:
            if tap not in up.student.taps:
                problems.append((f"{path}.aux.{name}.inputs", f"stage {aux.from_!r}'s {up.student.adapter!r} has no tap "
                                                              f"{tap!r} (it has: {', '.join(up.student.taps)})"))
        out.append(ResolvedAux(name, aux.from_, aux.which, up.student, inputs, aux.training))
    return out


def labels_problems(spec: Any, stages: dict[str, ResolvedStage], info: Any, path: str) -> list[tuple[str, str]]:
    """A ``labels`` edge: the upstream stage's predictions can be published, the fields exist; a stage's own
    ``publish``: its predictions can be."""
    from distilkit.engine.predictions import publishable

    out = []
    labels = spec.labels
    if labels is not None and labels.from_ in stages:
        up = stages[labels.from_].student
        kind = up.taps.get(up.cls.PREDICTION_TAP)
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
    missing = sorted(model.cls.inputs(model.params) - info.fields) if info.fields else []
    if missing:
        from distilkit.schema_doc import aux_only_inputs

        aux = aux_only_inputs(frozenset(missing))
        hint = (f"; no dataset provides {', '.join(aux)}: a frozen auxiliary model's tap does, e.g. `aux: {{{aux[0]}: "
                f"{{from: STAGE}}}}` (its prediction becomes the input `{aux[0]}`)" if aux else "")
        out.append((f"{path}.adapter", f"adapter {model.adapter!r} reads batch input(s) {', '.join(missing)}, which "
                                       f"the data does not provide (it has: {', '.join(sorted(info.fields))}){hint}"))
    out += [(f"{path}.params.{param}" if param else f"{path}.adapter", problem)
            for param, problem in model.cls.check_data(model.params, info)]
    return out


def resolve(recipe: Recipe, source: str = "recipe") -> ResolvedRecipe:
    """Check everything that can be checked without training; raise :class:`RecipeError` listing all problems."""
    problems: list[tuple[str, str]] = []
    try:
        order = stage_order(recipe)
    except RecipeError as exc:
        problems.extend(exc.problems)
        order = list(recipe.stages)
    ds = _lookup(DATASETS, recipe.data.dataset, "data.dataset", problems)
    data_params = _params(ds.meta["params"], recipe.data.params, "data.params", problems) if ds else None
    info = ds.meta["info"](data_params) if data_params is not None else None
    stages: dict[str, ResolvedStage] = {}
    for name in order:
        spec = recipe.stages[name]
        path = f"stages.{name}"
        student = _model(spec.model, f"{path}.model", problems)
        aux = resolve_aux(spec, stages, path, problems)
        problems.extend(labels_problems(spec, stages, info, path))
        if student is not None and spec.publish:
            from distilkit.engine.predictions import publishable

            kind = student.taps.get(student.cls.PREDICTION_TAP)
            if not publishable(kind):
                problems.append((f"{path}.publish", f"{student.adapter!r} predicts {kind}, which cannot be published "
                                                    "(voxel_logits and points can)"))
        stage_info = info
        if info is not None and aux:  # the auxiliary models' inputs are batch fields of this stage
            import dataclasses

            stage_info = dataclasses.replace(info, fields=info.fields | {f for a in aux for f in a.inputs.values()})
        teacher, teacher_from = None, None
        if spec.teacher is not None:
            if spec.teacher.from_ is not None:
                teacher_from = spec.teacher.from_
                up = stages.get(teacher_from)
                teacher = up.student if up else None
            else:
                assert spec.teacher.model is not None
                teacher = _model(spec.teacher.model, f"{path}.teacher.model", problems)
            if teacher is not None and spec.teacher.taps:  # this stage records more of the teacher
                teacher = ResolvedModel(teacher.adapter, teacher.cls, teacher.params,
                                        {**teacher.hooks, **spec.teacher.taps})
        models = {"student": student, "teacher": teacher}
        task_specs = spec.task_losses
        if task_specs is None and student is not None:
            task_specs = [LossSpec.model_validate(d) for d in student.cls.DEFAULT_TASK_LOSSES]
        task = _terms(task_specs or [], TASK_LOSSES, f"{path}.task_losses", models, stage_info, problems)
        distill = _terms(spec.distill, OBJECTIVES, f"{path}.distill", models, stage_info, problems)
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
        if info is not None:
            own_teacher = teacher if teacher_from is None else None  # a teacher stage was checked as a student
            for model, where in ((student, f"{path}.model"), (own_teacher, f"{path}.teacher.model")):
                if model is not None:
                    problems.extend(data_problems(model, stage_info, where))
        if info is not None:
            problems.extend(alignment_problems(distill, models, info, f"{path}.distill"))
        for i, term in enumerate(distill):  # teacher and student capabilities the objective calls
            for role, model, caps in (("teacher", teacher, term.cls.REQUIRES),
                                      ("student", student, term.cls.student_requires(term.params))):
                for cap in sorted(caps):
                    if model is not None and not callable(getattr(model.cls, cap, None)):
                        problems.append((f"{path}.distill[{i}]", f"{term.name} calls the {role}'s {cap}(), which "
                                                                  f"adapter {model.adapter!r} does not provide"))
        _lookup(OPTIMIZERS, spec.optimizer.name, f"{path}.optimizer.name", problems)
        schedule_entry = _lookup(SCHEDULES, spec.optimizer.schedule.name, f"{path}.optimizer.schedule.name", problems)
        schedule = None if schedule_entry is None else _params(schedule_entry.meta["params"], spec.optimizer.schedule.params,
                                                               f"{path}.optimizer.schedule.params", problems)
        if student is not None:
            groups = param_groups(spec.optimizer.param_groups, task, distill)
            stages[name] = ResolvedStage(name, spec, student, teacher, teacher_from, task, distill, groups, metric,
                                         schedule, [*([metric] if metric else []), *extras], hooks, aux)
    if problems:
        raise RecipeError(problems, source)
    assert data_params is not None
    return ResolvedRecipe(recipe, data_params, info, stages, order)
