"""The sweep file: a base recipe, the stage to vary, named variants and seeds (``distilkit sweep``).

Each variant becomes a recipe of its own (:func:`variant_data`): the base recipe with the sweep's and the
variant's overrides applied, cut to the varied stage and the stages it needs, the varied stage renamed to the
variant. All of them are named after the sweep, so they share one output folder, and an upstream stage (the
teacher) that is the same in several of them has one identity there: it is trained once and shared.
"""

from __future__ import annotations

import copy
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from distilkit.errors import RecipeError
from distilkit.recipe import (LossSpec, Recipe, needed_stages, parse_yaml, pydantic_problems, recipe_from_dict,
                              set_path, stage_order)

_NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class VariantSpec(_Strict):
    """One row of the comparison: distillation objectives, recipe overrides, or both."""

    label: str | None = Field(None, description="display name in the table (default: the variant's name)")
    distill: list[LossSpec] | None = Field(None, description="the varied stage's distillation objectives (replace the "
                                                              "recipe's; [] = no distillation)")
    set: dict[str, Any] = Field(default_factory=dict, alias="set",
                                description="recipe overrides by dotted path, e.g. {stages.student.optimizer.lr: 0.01}")
    controls: bool = Field(True, description="with the sweep's `controls`: whether this variant gets its control rows")
    _control: tuple[str, str] | None = PrivateAttr(None)  # (variant, kind) of a control row the sweep added


class LauncherSpec(_Strict):
    """How ``distilkit sweep --launcher slurm`` allocates each run (the command line's flags win)."""

    gpus_per_run: int | None = Field(None, ge=0, description="GPUs of one run (> 1: distilkit run --nproc-per-node)")
    cpus_per_run: int | None = Field(None, ge=1, description="CPUs of one run (its threads)")
    mem: str | None = Field(None, description="memory of one run, as sbatch --mem takes it (e.g. 32G)")
    time: str | int | None = Field(None, description="time limit of one job (minutes or D-HH:MM:SS); a longer run "
                                                     "is requeued from its checkpoint")
    partition: str | None = Field(None, description="Slurm partition")
    array_parallelism: int | None = Field(None, ge=1, description="runs of one array at a time")
    slurm: dict[str, str | int] = Field(default_factory=dict, description="any other sbatch option, e.g. "
                                                                          "{account: mylab, qos: high}")


def launcher_hint(value: Any) -> str:
    """Why ``launcher:`` must be a block: the launcher is chosen on the command line, the block holds resources."""
    got = f"{value!r}" if isinstance(value, (str, int, float, bool)) else f"a {type(value).__name__}"
    return (f"{got} is not a block: the launcher is chosen on the command line (`distilkit sweep FILE --launcher "
            f"slurm`); the sweep file's `launcher:` block holds each run's Slurm resources, with the keys "
            f"{', '.join(LauncherSpec.model_fields)} (e.g. launcher: {{gpus_per_run: 1, time: '8:00:00', slurm: "
            "{account: mylab}})")


class SweepSpec(_Strict):
    """A comparison of variants of one stage of a recipe over seeds."""

    schema_version: Literal[1] = Field(1, description="sweep file format version")
    name: str = Field(..., pattern=_NAME, description="sweep name (folder under the output)")
    recipe: str | dict[str, Any] = Field(..., description="the base recipe: a path (relative to the sweep file) or "
                                                          "the recipe itself")
    stage: str = Field(..., description="the stage of the base recipe whose variants are compared")
    teacher: str | None = Field(None, description="the stage the variants distil from (default: the varied stage's "
                                                  "own `teacher`)")
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1, description="training seeds "
                                                                                     "(`--seeds` overrides)")
    upstream: Literal["per_seed", "shared"] = Field(
        "per_seed", description="the stages the variants need (the teacher): trained once per seed, or once for "
                                "all seeds (at `upstream_seed`)")
    upstream_seed: int | None = Field(None, description="with upstream: shared, their seed (default: the recipe's)")
    baseline: str | None = Field(None, description="the variant the paired differences are taken to (default: the "
                                                   "first variant without distillation)")
    set: dict[str, Any] = Field(default_factory=dict, alias="set",
                                description="overrides by dotted path applied to the base recipe for every variant")
    variants: dict[str, VariantSpec] = Field(..., min_length=1, description="name -> variant, in table order")
    controls: list[Literal["random", "shuffled"]] = Field(
        default_factory=list, description="control teachers (`teacher.control`): after each variant that distils "
                                          "from a teacher, the same variant against each control, as `<variant>."
                                          "<control>` (a variant's `controls: false` leaves it out)")
    launcher: LauncherSpec | None = Field(None, description="resources of each run on a cluster "
                                                            "(`--launcher slurm`)")

    @field_validator("launcher", mode="before")
    @classmethod
    def _launcher_block(cls, value: Any) -> Any:
        """``launcher: slurm`` (a name where the block of resources goes): say where the launcher is chosen."""
        if value is None or isinstance(value, (dict, LauncherSpec)):
            return value
        raise ValueError(launcher_hint(value))

    @model_validator(mode="after")
    def _names(self) -> "SweepSpec":
        bad = [n for n in self.variants if not re.fullmatch(_NAME, n)]
        if bad:
            raise ValueError(f"variant name {bad[0]!r} must be letters, digits, '_', '-' or '.'")
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds: give each seed once, got {self.seeds}")
        if self.baseline is not None and self.baseline not in self.variants:
            raise ValueError(f"baseline {self.baseline!r} is not a variant (variants: {', '.join(self.variants)})")
        return self


class Sweep:
    """A loaded sweep: the spec, its base recipe (as data) and one recipe per variant."""

    def __init__(self, spec: SweepSpec, base: dict[str, Any], source: str) -> None:
        spec = spec.model_copy()  # the caller's spec keeps its variants; this copy gains the control rows
        self.spec, self.base, self.source = spec, base, source
        spec.variants = {n: v for n, v in spec.variants.items() if v._control is None}  # the file's, then controls
        self.data: dict[str, dict[str, Any]] = {name: variant_data(self, name) for name in spec.variants}
        spec.variants = with_controls(self)  # each control row after its variant, in the table's order
        self.data = {name: self.data.get(name) or variant_data(self, name) for name in spec.variants}
        self.recipes: dict[str, Recipe] = {name: recipe_from_dict(d, source) for name, d in self.data.items()}

    @property
    def name(self) -> str:
        return self.spec.name

    def label(self, variant: str) -> str:
        return self.spec.variants[variant].label or variant

    @property
    def baseline(self) -> str | None:
        """The named baseline, else the first variant whose stage has no distillation."""
        if self.spec.baseline is not None:
            return self.spec.baseline
        return next((n for n, r in self.recipes.items() if not r.stages[n].distill), None)

    @property
    def controls(self) -> dict[str, tuple[str, str]]:
        """Each control row the sweep added: its variant and control kind."""
        return {n: v._control for n, v in self.spec.variants.items() if v._control is not None}

    def upstream_stages(self, variant: str) -> list[str]:
        """The stages a variant's recipe runs before the variant itself (its teacher, ...)."""
        return [n for n in stage_order(self.recipes[variant]) if n != variant]


def variant_data(sweep: Sweep, variant: str) -> dict[str, Any]:
    """The recipe of one variant, as data (see the module docstring); a problem is named with the variant."""
    spec, where = sweep.spec, f"variants.{variant}"
    data = copy.deepcopy(sweep.base)
    for path, value in spec.set.items():
        set_path(data, path, value, sweep.source, "set")
    chosen = spec.variants[variant]
    for path, value in chosen.set.items():
        set_path(data, path, value, sweep.source, f"{where}.set")
    stages = data.get("stages") if isinstance(data.get("stages"), dict) else {}
    if spec.stage not in stages:
        raise RecipeError([("stage", f"the base recipe has no stage {spec.stage!r} (stages: {', '.join(stages)})")],
                          sweep.source)
    stage = stages[spec.stage]
    if not isinstance(stage, dict):
        raise RecipeError([(where, f"stage {spec.stage!r} of the recipe is a {type(stage).__name__}, not a mapping")],
                          sweep.source)
    if chosen.distill is not None:
        stage["distill"] = [t.model_dump(mode="json", by_alias=True, exclude_none=True, exclude_defaults=True)
                            for t in chosen.distill]
    own = isinstance(stage.get("teacher"), dict) and stage["teacher"].get("ema") not in (None, False)
    if spec.teacher is not None and stage.get("distill") and not own:  # a variant that is its own teacher keeps it
        given = stage["teacher"] if isinstance(stage.get("teacher"), dict) else {}
        stage["teacher"] = {**given, "from": spec.teacher}  # the sweep's teacher, with the recipe's other settings
        # of it (store, mode, checkpoint) and the variant's
    if not stage.get("distill"):  # no distillation: no teacher, so the run does not depend on one
        stage.pop("teacher", None)
    elif not stage.get("teacher"):
        raise RecipeError([(where, f"distils, but stage {spec.stage!r} has no teacher: give the sweep "
                                   "`teacher: STAGE`")], sweep.source)
    if variant != spec.stage and variant in stages:
        raise RecipeError([(where, f"variant {variant!r} has the name of a stage of the base recipe; rename it")],
                          sweep.source)
    data["name"] = spec.name
    try:
        full = recipe_from_dict(data, sweep.source)
        order = stage_order(full)  # every teacher/init stage exists, no cycles
    except RecipeError as err:
        raise RecipeError([(f"{where} (recipe {p})" if p else where, m) for p, m in err.problems], sweep.source) from None
    needed = needed_stages(full, {spec.stage})
    kept = {(variant if n == spec.stage else n): copy.deepcopy(stages[n]) for n in order if n in needed}
    if spec.upstream == "shared":
        seed = spec.upstream_seed if spec.upstream_seed is not None else full.seed
        for n in kept:
            if n != variant:
                kept[n]["seed"] = seed
    if chosen.label is not None:
        kept[variant]["label"] = chosen.label
    data["stages"] = kept
    return data


def with_controls(sweep: Sweep) -> dict[str, VariantSpec]:
    """The variants with, after each that distils from a teacher of its own (not its moving average), one row per
    control of ``controls`` it can take: the variant with ``teacher.control`` set
    (:mod:`distilkit.engine.train.controls`; a random teacher runs live, without the variant's ``store``). A variant
    whose terms call the teacher themselves, or read no teacher tap, gets no shuffled row (there is nothing the
    shuffle reaches: ``validate`` would refuse it)."""
    out: dict[str, VariantSpec] = {}
    for name, variant in sweep.spec.variants.items():
        out[name] = variant
        stage = sweep.data[name]["stages"][name]
        teacher = stage.get("teacher")
        if (not variant.controls or not stage.get("distill") or not isinstance(teacher, dict)
                or teacher.get("ema") not in (None, False)):
            continue
        for kind in sweep.spec.controls:
            if kind == "shuffled" and not _shuffles(stage["distill"]):
                continue
            added = f"{name}.{kind}"
            if added in sweep.spec.variants:
                raise RecipeError([(f"variants.{added}", f"has the name of the {kind} control row of variant "
                                                         f"{name!r}: rename it")], sweep.source)
            where = f"stages.{sweep.spec.stage}.teacher"
            row = VariantSpec(label=f"{sweep.label(name)} · {kind} teacher", distill=variant.distill,
                              set={**variant.set, f"{where}.control": kind,
                                   **({f"{where}.store": None} if kind == "random" else {})})
            row._control = (name, kind)
            out[added] = row
    return out


def _shuffles(distill: list[Any]) -> bool:
    """Whether a shuffled teacher reaches the terms: none calls the teacher itself and one reads a teacher tap
    (unknown names: left to the recipe's own check)."""
    from distilkit.errors import UnknownNameError
    from distilkit.registry import OBJECTIVES

    cards = []
    for term in distill:
        try:
            cards.append(OBJECTIVES.entry(str(term.get("name") if isinstance(term, dict) else term)).card)
        except UnknownNameError:
            return True
    return not any(c.REQUIRES for c in cards) and any(c.TEACHER_ROLES for c in cards)


def load_sweep(path: str | Path) -> Sweep:
    """Read a sweep file (``yaml.safe_load``) and build every variant's recipe; problems are RecipeErrors."""
    path = Path(path)
    source = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecipeError([("", f"cannot read sweep file: {exc}")], source) from None
    data = parse_yaml(text, source)
    if not isinstance(data, dict):
        raise RecipeError([("", f"a sweep file must be a YAML mapping, got {type(data).__name__}")], source)
    try:
        spec = SweepSpec.model_validate(data)
    except ValidationError as err:
        raise RecipeError(pydantic_problems(err, model=SweepSpec), source) from None
    if isinstance(spec.recipe, str):
        base_path = (path.parent / spec.recipe) if not Path(spec.recipe).is_absolute() else Path(spec.recipe)
        try:
            base = parse_yaml(base_path.read_text(encoding="utf-8"), str(base_path))
        except (OSError, UnicodeDecodeError) as exc:
            raise RecipeError([("recipe", f"cannot read the base recipe: {exc}")], source) from None
        if not isinstance(base, dict):
            raise RecipeError([("recipe", f"{base_path} is not a recipe (a YAML mapping)")], source)
    else:
        base = spec.recipe
    return Sweep(spec, base, source)


__all__ = ["LauncherSpec", "Sweep", "SweepSpec", "VariantSpec", "load_sweep", "set_path", "variant_data",
           "with_controls"]
