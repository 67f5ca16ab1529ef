"""A stage's models and terms against the registries: each name looked up, each parameter model validated, each
term's roles bound to its models' taps and the batch's fields, the student's and the teacher's taps checked to align
on one grid, and the optimizer's parameter groups — every problem collected with its recipe path."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError

from distilkit.cards.base import partner as student_partner
from distilkit.engine.assemble.resolved import ResolvedModel, ResolvedTerm
from distilkit.errors import UnknownNameError
from distilkit.recipe import LossSpec, ModelSpec, ParamGroupSpec, pydantic_problems
from distilkit.registry import ADAPTERS, CONNECTORS, RECORDERS, Registry
from distilkit.taps import DENSE_GRID_KINDS, TAP_KINDS, kind_fits


def lookup(reg: Registry[Any], name: str, path: str, problems: list[tuple[str, str]]) -> Any:
    try:
        return reg.entry(name)
    except UnknownNameError as exc:
        problems.append((path, str(exc)))
        return None


def validate_params(model: type[BaseModel], raw: dict[str, Any], path: str, problems: list[tuple[str, str]]) -> BaseModel | None:
    try:
        return model.model_validate(raw)
    except ValidationError as err:
        problems.extend(pydantic_problems(err, path, model=model))
        return None


def resolve_model(spec: ModelSpec, path: str, problems: list[tuple[str, str]]) -> ResolvedModel | None:
    entry = lookup(ADAPTERS, spec.adapter, f"{path}.adapter", problems)
    if entry is None:
        return None
    params = validate_params(entry.card.Params, spec.params, f"{path}.params", problems)
    problems.extend(hook_problems(entry.name, entry.card, {}, spec.taps, f"{path}.taps"))
    return None if params is None else ResolvedModel(entry.name, entry.card, params, dict(spec.taps))


VOXEL_KINDS = ("sparse_features", *sorted(DENSE_GRID_KINDS))  # what a tap can be collapsed from


def hook_problems(adapter: str, card: Any, known: dict[str, Any], hooks: dict[str, Any],
                  path: str) -> list[tuple[str, str]]:
    """What is wrong with a recipe's ``hooks`` (``taps:``) of a model whose adapter already has ``card.TAPS`` and the
    recipe taps ``known``: a name taken, an unknown kind or recorder, a tap made ``of`` one that is not a voxel tap of
    the model."""
    out = []
    kinds = {**card.TAPS, **{n: h.kind for n, h in known.items()}, **{n: h.kind for n, h in hooks.items()}}
    for name, hook in hooks.items():
        if name in card.TAPS:
            out.append((f"{path}.{name}", f"adapter {adapter!r} already has a tap {name!r}"))
        if hook.kind not in TAP_KINDS:
            out.append((f"{path}.{name}.kind", f"unknown tap kind {hook.kind!r} (registered: {', '.join(TAP_KINDS)})"))
        if hook.of is not None:
            source = kinds.get(hook.of)
            if source is None:
                out.append((f"{path}.{name}.of", f"the model has no tap {hook.of!r} (it has: {', '.join(kinds)})"))
            elif source not in VOXEL_KINDS or hook.of == name:
                out.append((f"{path}.{name}.of", f"tap {hook.of!r} is {source}: only a voxel tap ({', '.join(VOXEL_KINDS)}) "
                                                 "collapses over height"))
            continue
        recorder = lookup(RECORDERS, hook.at, f"{path}.{name}.at", out)
        if recorder is not None and recorder.name == "method" and not hook.method:
            out.append((f"{path}.{name}.method", "`at: method` needs the method's name"))
    return out


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


HEIGHT_CONNECTORS = ("height_max", "height_mean")  # a student voxel tap through one of them is a bird's-eye map


def _resolve_taps(term_path: str, cls: Any, given: dict[str, str], models: dict[str, ResolvedModel | None],
                  problems: list[tuple[str, str]], collapsed: bool = False) -> dict[str, str]:
    """Pick the tap of each role: the recipe's choice (checked) or the model's first tap of that kind
    (``collapsed``: the student's tap goes through a height connector first, so a voxel tap serves a bird's-eye
    role)."""
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
        if collapsed and role == "student":  # what the connector makes of each voxel tap
            taps = {n: "bev_features" if k in VOXEL_KINDS else k for n, k in taps.items()}
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


def resolve_terms(specs: list[LossSpec], reg: Registry[Any], path: str, models: dict[str, ResolvedModel | None],
           info: Any, problems: list[tuple[str, str]]) -> list[ResolvedTerm]:
    out = []
    for i, spec in enumerate(specs):
        p = f"{path}[{i}]"
        entry = lookup(reg, spec.name, f"{p}.name", problems)
        if entry is None:
            continue
        params = validate_params(entry.card.Params, spec.params, f"{p}.params", problems)
        connector = getattr(spec, "connector", None) or getattr(entry.card, "DEFAULT_CONNECTOR", None)
        if connector not in (None, "none"):
            found = lookup(CONNECTORS, connector, f"{p}.connector", problems)
            connector = found.name if found is not None else connector
        taps = _resolve_taps(p, entry.card, spec.taps, models, problems, connector in HEIGHT_CONNECTORS)
        student = models.get("student")
        if connector in HEIGHT_CONNECTORS and student is not None and "student" in taps and \
                student.taps.get(taps["student"]) not in VOXEL_KINDS:
            problems.append((f"{p}.connector", f"{connector} collapses a voxel tap over height; the student tap "
                                               f"{taps['student']!r} is {student.taps.get(taps['student'])}"))
        fields = _resolve_fields(p, entry.card, spec.taps, info, problems)
        weight = spec.weight if spec.weight is not None else float(getattr(entry.card, "DEFAULT_WEIGHT", 1.0))
        if params is not None:
            if connector not in (None, "none") and not entry.card.TEACHER_ROLES:
                problems.append((f"{p}.connector", f"{spec.name} reads no teacher tap: there is nothing to project to"))
            seen = sum(t.name == entry.name for t in out)
            out.append(ResolvedTerm(entry.name, entry.card, params, weight, taps,
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
    from distilkit.geometry.grids import grid_factors, plane_factors

    out = []
    s_model, t_model = models.get("student"), models.get("teacher")
    if s_model is None or t_model is None:
        return out
    for i, term in enumerate(terms):
        for role, tap in term.taps.items():
            # a teacher role pairs with the student role of the same suffix (teacher_logits: student_logits)
            partner = student_partner(role) if role in term.card.TEACHER_ROLES else None
            if partner not in term.taps:
                continue
            s_tap = term.taps[partner]
            where = f"{term.name}: student tap {s_tap!r} ({s_model.adapter}) and teacher tap {tap!r} ({t_model.adapter})"
            s_cam = s_model.card.tap_camera(s_tap, s_model.params, info)
            t_cam = t_model.card.tap_camera(tap, t_model.params, info)
            if s_cam is not None and t_cam is not None and s_cam != t_cam:
                out.append((f"{path}[{i}]", f"{where} see through cameras {_camera_text(s_cam)} and "
                                            f"{_camera_text(t_cam)}: image features of different cameras (or frames) "
                                            "cannot be compared pixel by pixel"))
            kind, s_kind = term.card.CONSUMES[role], term.card.CONSUMES[partner]
            height = partner == "student" and term.connector in HEIGHT_CONNECTORS
            s_tap_kind, t_tap_kind = ("bev_features" if height else s_model.taps.get(s_tap)), t_model.taps.get(tap)
            collapses = s_kind == "bev_features" and kind in VOXEL_KINDS  # the term collapses the teacher's itself
            if not collapses and {s_tap_kind, t_tap_kind} & {"bev_features"} and {s_tap_kind, t_tap_kind} & set(
                    VOXEL_KINDS):
                out.append((f"{path}[{i}]", f"{where} are a bird's-eye map and a volume ({s_tap_kind} and "
                                            f"{t_tap_kind}): give the volume a bird's-eye tap (`taps: {{bev: {{of: "
                                            "..., kind: bev_features, collapse: max}}`) or the student `connector: "
                                            "height_max`"))
                continue
            (s_grid, s_plane), (t_grid, t_plane) = tap_grid(s_model, s_tap, info), tap_grid(t_model, tap, info)
            s_plane = s_plane or height
            if s_grid is None or t_grid is None:
                continue
            if s_plane or t_plane:  # a bird's-eye plane pairs with the other's plane (a volume: its (X, Y))
                how = plane_factors(s_grid, t_grid)
                if isinstance(how, str) or ("bev_features" in (kind, s_kind) and how[0] != "same"):
                    why = how if isinstance(how, str) else f"{term.name} compares the maps cell by cell: one plane"
                    out.append((f"{path}[{i}]", f"{where}: their bird's-eye planes {tuple(s_grid.shape[:2])} and "
                                                f"{tuple(t_grid.shape[:2])} cannot be aligned: {why}"))
                continue
            how = grid_factors(s_grid, t_grid)
            if isinstance(how, str) or (kind == "voxel_logits" and how[0] != "same"):
                why = how if isinstance(how, str) else f"{kind} must share one grid"
                out.append((f"{path}[{i}]", f"{where} on grids {_grid_text(s_grid)} and {_grid_text(t_grid)} cannot "
                                            f"be aligned: {why}"))
    return out


def tap_grid(model: ResolvedModel, tap: str, info: Any) -> tuple[Any, bool]:
    """The voxel grid a tap lives on (None: not on one, or not known before training) and whether the tap is that
    grid's bird's-eye plane (a tap collapsed over height, or a ``bev_features`` tap)."""
    hook = model.hooks.get(tap)
    if hook is not None and getattr(hook, "of", None) is not None:
        return tap_grid(model, hook.of, info)[0], True
    grid = model.card.tap_grid(tap, model.params, info)
    return grid, model.taps.get(tap) == "bev_features"


def param_groups(given: list[Any] | None, task: list[ResolvedTerm], distill: list[ResolvedTerm]) -> list[dict[str, Any]]:
    """The optimizer's parameter groups: the recipe's, or else those the stage's terms ask for."""
    if given is not None:
        return [g.model_dump() for g in given]
    out = []
    for prefix, terms in (("task", task), ("distill", distill)):
        for t in terms:
            for g in getattr(t.card, "DEFAULT_PARAM_GROUPS", []):
                out.append(ParamGroupSpec.model_validate({**g, "match": f"{prefix}.{t.key}.{g['match']}"}).model_dump())
    return out

