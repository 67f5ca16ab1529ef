"""The recipe schema (pydantic v2): the single source of truth for configuration.

Recipes are read with ``yaml.safe_load`` only and may name registered components only.
:func:`load_recipe` parses and validates the structure (with ``--set`` overrides applied first); :func:`distilkit.engine.assemble.resolve.resolve` then builds
every parameter model from the registries and checks taps, so that mistakes are found before training.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from distilkit.errors import RecipeError

SCHEMA_VERSION = 1
MAX_NAME = 128  # recipe and stage names name folders (<stage>-<hash>: within the 255 bytes a file name may have)
MAX_LABEL = 200  # what reports show of a stage
MAX_NOTE = 1000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class HookTapSpec(_Strict):
    """A tap recorded from any submodule by its dotted path (no adapter code needed)."""

    module: str = Field(..., description="dotted path of the submodule, as in `model.named_modules()`")
    kind: str = Field(..., description="tap kind of the recorded value (e.g. volume_features)")
    at: str = Field("output", description="what is recorded: a registered recorder (`distilkit list recorders`): "
                                         "output, input (its first), method (the return value of `method`)")
    method: str | None = Field(None, description="with `at: method`: the submodule's method whose return value is "
                                                 "recorded (e.g. encode)")


class ModelSpec(_Strict):
    """A model: a registered adapter and its parameters."""

    adapter: str = Field(..., description="registered adapter name (see `distilkit list`)")
    params: dict[str, Any] = Field(default_factory=dict, description="the adapter's parameters")
    taps: dict[str, HookTapSpec] = Field(default_factory=dict,
                                         description="extra taps recorded from submodules by forward hooks")


class TeacherSpec(_Strict):
    """Where a stage's frozen teacher comes from: an earlier stage or a checkpoint file."""

    from_: str | None = Field(None, alias="from", description="name of an earlier stage whose best model is the teacher")
    checkpoint: str | None = Field(None, description="path of a distilkit checkpoint (loaded with weights_only=True)")
    model: ModelSpec | None = Field(None, description="the teacher's model (required with `checkpoint`)")
    which: Literal["best", "last"] = Field("best", description="checkpoint of the upstream stage to use")
    taps: dict[str, HookTapSpec] = Field(default_factory=dict,
                                         description="extra teacher taps recorded from submodules by forward hooks")

    @model_validator(mode="after")
    def _one_source(self) -> "TeacherSpec":
        if (self.from_ is None) == (self.checkpoint is None):
            raise ValueError("give exactly one of `from` (an earlier stage) or `checkpoint` (a file)")
        if self.checkpoint is not None and self.model is None:
            raise ValueError("a `checkpoint` teacher needs `model` (adapter and params)")
        return self


class InitSpec(_Strict):
    """Where a stage's student starts from (instead of random weights): an earlier stage or a weights file."""

    from_: str | None = Field(None, alias="from", description="name of an earlier stage whose weights the student "
                                                              "starts from (ScoreLiDAR: the teacher)")
    which: Literal["best", "last"] = Field("best", description="checkpoint of the upstream stage to use")
    checkpoint: str | None = Field(None, description="a weights file, read by the adapter's `read_weights` (a "
                                                     "distilkit checkpoint or a state dict; weights_only=True)")
    strict: bool = Field(True, description="every weight must fit the student (false: load the ones that fit by "
                                           "name and shape, and list the rest in the log)")

    @model_validator(mode="after")
    def _one_source(self) -> "InitSpec":
        if (self.from_ is None) == (self.checkpoint is None):
            raise ValueError("give exactly one of `from` (an earlier stage) or `checkpoint` (a file)")
        return self


class LabelsSpec(_Strict):
    """Training labels from an earlier stage's published predictions (Scribble2Scene's student on the
    Dean-Labeler's pseudo-labels), overlaid on the data by sample id; the data's own labels in ``keep`` win."""

    from_: str = Field(..., alias="from", description="the stage whose best model's predictions are the labels")
    field: str = Field("voxel_label", description="the sample field the predictions replace")
    keep: str | None = Field(None, description="a sample field whose labelled values win over the predictions "
                                               "(e.g. scribble): where it is neither the ignore index nor "
                                               "`unlabelled`")
    unlabelled: int | None = Field(254, description="the value of `keep` that means no label (ScribbleSC: 254)")
    splits: list[Literal["train", "val", "test"]] = Field(["train"], min_length=1,
                                                          description="the splits whose labels are replaced "
                                                                      "(evaluation keeps the data's own by default)")


class AuxSpec(_Strict):
    """A frozen auxiliary model from an earlier stage (VoxFormer's query proposals): it runs on every batch before
    the student, and its taps become batch inputs the student's adapter reads."""

    from_: str = Field(..., alias="from", description="the stage whose model is used, frozen")
    which: Literal["best", "last"] = Field("best", description="its checkpoint")
    inputs: dict[str, str] = Field(default_factory=dict, description="its tap -> the batch input it becomes "
                                                                     "(default: its prediction tap -> this aux "
                                                                     "model's name)")
    training: bool = Field(True, description="run it on the training batches too; false: only when evaluating and "
                                             "publishing (a model trained on other inputs and scored on this one's "
                                             "output, e.g. LiDiff's refinement trained on jittered ground truth)")


class LossSpec(_Strict):
    """A weighted term: a task loss or a distillation objective."""

    name: str = Field(..., description="registered name")
    weight: float | None = Field(None, ge=0, description="weight (default: the component's default)")
    params: dict[str, Any] = Field(default_factory=dict, description="the component's parameters")
    taps: dict[str, str] = Field(default_factory=dict,
                                 description="role -> tap name, e.g. {student: completion, teacher: completion}; "
                                             "for a batch role, the batch field, e.g. {target: voxel_label}")
    connector: str | None = Field(
        None, description="learnable projection of the student tap to the teacher's channels before the objective: a "
                          "registered connector (linear, mlp, conv3, or a plugin's; `distilkit list connectors`) or "
                          "none (default: the objective's own; fitnets: linear)")
    warmup_steps: int = Field(0, ge=0, description="the weight grows linearly over the first N steps (mdistiller's "
                                                   "warm-up of the distillation weight); 0: the full weight at once")


class ParamGroupSpec(_Strict):
    """Parameters whose qualified name matches ``match`` (a glob over ``student.<module path>``,
    ``task.<term>.<param>``, ``distill.<objective>.<param>``; a bare name matches its last part)."""

    match: str = Field(..., min_length=1, description="glob, e.g. 'task.uncertainty_multitask.log_var' or 'log_var'")
    lr_scale: float = Field(1.0, ge=0, description="learning rate = optimizer lr x lr_scale (0: frozen, as `freeze`)")
    weight_decay: float | None = Field(None, ge=0, description="(default: the optimizer's)")


class ScheduleSpec(_Strict):
    """The learning rate over the steps: a registered schedule (`distilkit list schedules`) and a linear warm-up."""

    name: str = Field("constant", description="registered schedule: constant, step, cosine, or a plugin's")
    params: dict[str, Any] = Field(default_factory=dict, description="the schedule's parameters "
                                                                     "(step: step_size, gamma; cosine: min_factor)")
    warmup_steps: int = Field(0, ge=0, description="linear warm-up over the first N steps, times the schedule")


class OptimizerSpec(_Strict):
    name: str = Field("adam", description="registered optimizer: adam, adamw, sgd, or a plugin's")
    lr: float = Field(1e-3, gt=0)
    weight_decay: float = Field(0.0, ge=0)
    momentum: float = Field(0.9, ge=0, description="SGD only")
    betas: tuple[float, float] = (0.9, 0.999)
    param_groups: list[ParamGroupSpec] | None = Field(
        None, description="per-group learning rates, first match wins (default: the groups the stage's terms ask "
                          "for, e.g. JS3C-Net's sigma at 10x; [] for none)")
    schedule: ScheduleSpec = Field(default_factory=ScheduleSpec, description="learning-rate schedule")


class HookSpec(_Strict):
    """A registered lifecycle hook of the training loop (`distilkit list hooks`), e.g. the TensorBoard logger."""

    name: str = Field(..., description="registered hook: tensorboard, or a plugin's")
    params: dict[str, Any] = Field(default_factory=dict, description="the hook's parameters")


class TrainSpec(_Strict):
    epochs: int | None = Field(None, ge=1, description="passes over the training split")
    steps: int | None = Field(None, ge=0, description="optimizer steps (instead of epochs); 0 = evaluate only (a "
                                                      "model from `init` scored as it is, e.g. at other sampler steps)")
    batch_size: int = Field(1, ge=1)
    grad_clip: float | None = Field(None, gt=0, description="max gradient norm (SCPNet: 10)")
    eval_every: int | None = Field(None, ge=1, description="evaluate every N steps (default: end of each epoch)")
    log_every: int = Field(10, ge=1)
    checkpoint_every: int = Field(20, ge=1, description="write last.pt every N steps (and at each evaluation)")
    device: str = Field("auto", description="'auto' (cuda if available), 'cpu' or 'cuda'")
    precision: Literal["fp32", "bf16", "fp16"] = Field(
        "fp32", description="the models' forward passes under autocast in this precision; loss terms run in float32 "
                            "(Gram-based objectives keep their float64 accumulation); fp16 uses a gradient scaler")
    metric: str = Field("miou", description="validation score that selects best.pt: a score of the metric for the "
                                            "adapter's prediction kind ('miou', 'iou', ...), or 'METRIC.SCORE' "
                                            "('ssc.miou'); see `distilkit list metrics`. Left out: miou, or where "
                                            "no metric of the prediction kind has one, its first score (cd for "
                                            "point clouds)")
    metrics: list[str] = Field(default_factory=list, description="further registered metrics scored at every "
                                                                 "evaluation beside `metric`'s (reported as "
                                                                 "METRIC.SCORE)")
    workers: int | Literal["auto"] = Field("auto", description="data-loader processes that read and collate batches "
                                                               "(0: in the stage's process; auto: none on 2 CPUs or "
                                                               "fewer, else half the CPUs beyond two, at most 4); "
                                                               "the numbers do not depend on it")
    hooks: list[HookSpec] = Field(default_factory=list, description="registered lifecycle hooks run after the "
                                                                    "stage's own (log, progress, evaluation, "
                                                                    "checkpoint), e.g. {name: tensorboard}")

    @field_validator("workers")
    @classmethod
    def _workers(cls, v: int | str) -> int | str:
        if isinstance(v, int) and v < 0:
            raise ValueError("workers must be 0 or more, or 'auto'")
        return v

    @model_validator(mode="after")
    def _length(self) -> "TrainSpec":
        if self.epochs is None and self.steps is None:
            self.epochs = 1
        if self.epochs is not None and self.steps is not None:
            raise ValueError("give either `epochs` or `steps`, not both")
        return self


class StageSpec(_Strict):
    """One training stage: a student model, optionally a frozen teacher and distillation terms."""

    model: ModelSpec
    init: InitSpec | None = Field(None, description="start the student from weights instead of random ones")
    teacher: TeacherSpec | None = None
    task_losses: list[LossSpec] | None = Field(None, description="supervised terms (default: the adapter's)")
    distill: list[LossSpec] = Field(default_factory=list, description="distillation objectives")
    optimizer: OptimizerSpec = Field(default_factory=OptimizerSpec)
    train: TrainSpec = Field(default_factory=TrainSpec)
    freeze: list[str] = Field(default_factory=list, description="globs of trainable parameters to keep as they "
                                                                "are, by qualified name (student.<module path>..., "
                                                                "as param_groups' match), e.g. 'student.net.encoder.*'")
    labels: LabelsSpec | None = Field(None, description="training labels from an earlier stage's predictions")
    aux: dict[str, AuxSpec] = Field(default_factory=dict, description="frozen auxiliary models from earlier stages, "
                                                                      "by name; their taps become batch inputs")
    publish: list[Literal["train", "val", "test"]] = Field(
        default_factory=list, description="splits whose predictions the stage's best model publishes by sample id "
                                          "(a stage that a later stage reads labels from publishes what it needs)")
    label: str | None = Field(None, max_length=MAX_LABEL, description=f"display name in reports (at most {MAX_LABEL} "
                                                                        "characters)")
    seed: int | None = Field(None, description="this stage's training seed (default: the recipe's `seed`, or "
                                               "`--seed`); a sweep fixes a shared teacher's seed this way")

    @model_validator(mode="after")
    def _teacher_needed(self) -> "StageSpec":
        if self.distill and self.teacher is None:
            raise ValueError("`distill` objectives need a `teacher`")
        return self

    def edges(self) -> dict[str, str]:
        """Every upstream edge of the stage, field -> the stage it reads (``teacher``: its frozen model, ``init``:
        its weights, ``labels``: its published predictions, ``aux.NAME``: its frozen model as an auxiliary
        network). Ordering, needed stages, ``downstream``, ``--stage``, resolution and identity read only this."""
        out = {field: src.from_ for field, src in (("teacher", self.teacher), ("init", self.init),
                                                   ("labels", self.labels))
               if src is not None and src.from_ is not None}
        return {**out, **{f"aux.{name}": aux.from_ for name, aux in self.aux.items()}}


class DataSpec(_Strict):
    dataset: str = Field("synthetic-lidar", description="registered dataset name")
    params: dict[str, Any] = Field(default_factory=dict, description="the dataset's parameters")


class ReportSpec(_Strict):
    """How the recipe's report shows its stages beyond the results table."""

    per_class: bool = Field(False, description="also print and write the papers' layout: one row per stage, its "
                                               "scores and then every class's score (best checkpoint, test split)")
    compare: dict[str, str] = Field(default_factory=dict, description="stage -> the stage its paired differences over "
                                                                      "seeds are taken to (e.g. a few-step student -> "
                                                                      "the undistilled teacher at the same step "
                                                                      "count; default: the seeds' baseline)")
    note: str | None = Field(None, max_length=MAX_NOTE, description="a line printed under the results table and "
                                                                    "written under it in report.md (e.g. how much "
                                                                    "one run of the recipe can tell)")


class Recipe(_Strict):
    """A distilkit recipe: data and named stages, run in dependency order."""

    schema_version: Literal[1] = Field(SCHEMA_VERSION, description="recipe format version")
    name: str = Field(..., pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", max_length=MAX_NAME,
                      description=f"run name (folder under the output; at most {MAX_NAME} characters)")
    seed: int = 0
    data: DataSpec = Field(default_factory=DataSpec)
    stages: dict[str, StageSpec] = Field(..., min_length=1)
    report: ReportSpec = Field(default_factory=ReportSpec)

    @field_validator("stages")
    @classmethod
    def _stage_names(cls, v: dict[str, StageSpec]) -> dict[str, StageSpec]:
        import re

        for name in v:
            if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name):
                raise ValueError(f"stage name {name[:40]!r}{'...' if len(name) > 40 else ''} must be letters, digits, "
                                 "'_', '-' or '.'")
            if len(name) > MAX_NAME:  # <stage>-<hash> must be a folder name (255 bytes at most)
                raise ValueError(f"stage name {name[:40]!r}... has {len(name)} characters: at most {MAX_NAME} (it "
                                 "names a folder)")
        return v

    @model_validator(mode="after")
    def _compared_stages(self) -> "Recipe":
        for stage, ref in self.report.compare.items():
            unknown = [n for n in (stage, ref) if n not in self.stages]
            if unknown:
                raise ValueError(f"report.compare: {', '.join(map(repr, unknown))} is not a stage of the recipe "
                                 f"(stages: {', '.join(self.stages)})")
            if stage == ref:
                raise ValueError(f"report.compare: stage {stage!r} is compared with itself")
        return self


def format_loc(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _model_at(model: Any, loc: tuple[Any, ...]) -> type[BaseModel] | None:
    """The pydantic model class a location inside ``model`` (a class) falls in: field by field, through the values
    of dicts (a part of ``loc`` is then their key) and the items of lists (an index), None where it leaves them."""
    import typing

    def unwrap(annotation: Any) -> tuple[Any, bool]:
        """(the model or container an annotation holds, whether the next part of the location is a key/index)."""
        origin = typing.get_origin(annotation)
        if origin in (dict, list):
            return typing.get_args(annotation)[-1], True
        inner = [a for a in typing.get_args(annotation) if a is not type(None)]
        if origin is not None and len(inner) == 1:  # Optional[X]
            return unwrap(inner[0])
        return annotation, False

    node: Any = model
    keyed = False
    for part in loc:
        if keyed:  # a dict's key or a list's index: its value's annotation
            node, keyed = unwrap(node)
            continue
        if not (isinstance(node, type) and issubclass(node, BaseModel)):
            return None
        field = node.model_fields.get(part) or next((f for f in node.model_fields.values() if f.alias == part), None)
        if field is None:
            return None
        node, keyed = unwrap(field.annotation)
    if keyed:
        return None
    return node if isinstance(node, type) and issubclass(node, BaseModel) else None


def model_keys(model: type[BaseModel]) -> list[str]:
    """The keys a model accepts, as a recipe writes them (aliases where a field has one)."""
    return sorted(f.alias or name for name, f in model.model_fields.items())


def unknown_key_message(key: Any, valid: list[str]) -> str:
    """``unknown key 'x'`` with the nearest valid key and the valid ones."""
    import difflib

    close = difflib.get_close_matches(str(key), valid, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown key {str(key)!r}{hint} (valid: {', '.join(valid)})"


def pydantic_problems(err: ValidationError, prefix: str = "", model: type[BaseModel] | None = None) -> \
        list[tuple[str, str]]:
    """(path, message) per validation error; an unknown key names the valid keys of ``model`` (the class validated)
    at its place, and the nearest one."""
    problems = []
    for e in err.errors():
        loc = tuple(p for p in e["loc"] if p not in ("function-after",) and not str(p).startswith("function-"))
        path = format_loc(loc)
        if prefix:
            path = f"{prefix}.{path}" if path and not path.startswith("[") else prefix + path
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            at = _model_at(model, loc[:-1]) if model is not None and loc else None
            msg = unknown_key_message(loc[-1], model_keys(at)) if at is not None and loc else "unknown key"
        elif msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        problems.append((path, msg))
    return problems


def parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise RecipeError([("", f"{where}malformed YAML: {problem}")], source) from None


def recipe_from_dict(data: Any, source: str = "recipe") -> Recipe:
    if not isinstance(data, dict):
        raise RecipeError([("", f"a recipe must be a YAML mapping, got {type(data).__name__}")], source)
    try:
        return Recipe.model_validate(data)
    except ValidationError as err:
        raise RecipeError(pydantic_problems(err, model=Recipe), source) from None


def set_path(data: dict[str, Any], path: str, value: Any, source: str, where: str) -> int:
    """Set ``data[a][b][0]...`` from the dotted path ``a.b.0...`` (mappings are created on the way); a ``*`` part
    stands for every key of the mapping (every item of the list) found there, as in ``stages.*.train.steps``.
    Returns the number of places set; a path whose wildcard matches nothing is an error that names it."""
    parts = path.split(".")
    if "*" in parts:
        places = _expand(data, parts)
        if not places:
            i = parts.index("*")
            raise RecipeError([(where, f"{path}: matches nothing (no field of the recipe is at that path; the first "
                                       f"'*' stands for the entries of {'.'.join(parts[:i]) or 'the recipe'})")],
                              source)
        for place in places:
            set_path(data, ".".join(place), value, source, where)
        return len(places)
    node = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise RecipeError([(where, f"{path}: {'.'.join(parts[:i]) or 'the recipe'} is a list of {len(node)}; "
                                           f"{part!r} is not an index of it")], source)
            key: Any = int(part)
        elif isinstance(node, dict):
            key = part
        else:
            raise RecipeError([(where, f"{path}: {'.'.join(parts[:i])} is a {type(node).__name__}, not a mapping or "
                                       "a list")], source)
        if last:
            node[key] = copy.deepcopy(value)
            return 1
        else:
            if isinstance(node, dict) and node.get(key) is None:
                if parts[:i] == ["stages"]:  # a new stage from a typo would fail later with a vaguer message
                    import difflib

                    close = difflib.get_close_matches(key, [str(k) for k in node], n=1)
                    hint = f"; did you mean {close[0]!r}?" if close else ""
                    raise RecipeError([(where, f"{path}: the recipe has no stage {key!r}{hint} (stages: "
                                               f"{', '.join(map(str, node)) or 'none'})")], source)
                node[key] = {}
            node = node[key]
    return 0  # not reached: the last part returns


def _expand(node: Any, parts: list[str]) -> list[list[str]]:
    """The concrete paths a dotted path with ``*`` parts names in ``node``: each ``*`` stands for every key of the
    mapping (item of the list) there; a branch that does not reach the path's last part names nothing."""
    if not parts:
        return [[]]
    head, rest = parts[0], parts[1:]
    if head == "*":
        keys = list(node) if isinstance(node, dict) else list(range(len(node))) if isinstance(node, list) else []
    else:
        keys = [head]
    out = []
    for key in keys:
        if not rest:
            out.append([str(key)])
            continue
        child = (node.get(key) if isinstance(node, dict) else
                 node[int(key)] if isinstance(node, list) and str(key).isdigit() and int(key) < len(node) else None)
        if child is None and "*" not in rest:  # created on the way, as a path without wildcards would be
            out.append([str(key), *rest])
        elif isinstance(child, (dict, list)):
            out += [[str(key), *tail] for tail in _expand(child, rest)]
    return out


def parse_overrides(items: list[str], source: str = "--set") -> dict[str, Any]:
    """``PATH=VALUE`` items of the command line (``stages.student.optimizer.lr=0.01``) as path -> value, each value
    read as YAML (``0.01`` a number, ``[1, 2]`` a list, ``true`` a boolean, anything else a string)."""
    out: dict[str, Any] = {}
    for item in items:
        path, eq, text = item.partition("=")
        if not eq or not path.strip() or any(not part for part in path.strip().split(".")):
            raise RecipeError([("--set", f"{item!r}: expected PATH=VALUE with a dotted path, e.g. "
                                         "stages.student.optimizer.lr=0.01")], source)
        out[path.strip()] = parse_yaml(text, f"--set {path.strip()}")
    return out


def load_recipe(path: str | Path, overrides: dict[str, Any] | None = None) -> Recipe:
    """Read and validate the structure of a recipe file (``yaml.safe_load``; nothing is executed), with
    ``overrides`` (dotted path -> value, :func:`parse_overrides`) applied first and validated like the file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecipeError([("", f"cannot read recipe: {exc}")], str(path)) from None
    data = parse_yaml(text, str(path))
    if overrides:
        if not isinstance(data, dict):
            raise RecipeError([("", f"a recipe must be a YAML mapping, got {type(data).__name__}")], str(path))
        for key, value in overrides.items():
            set_path(data, key, value, str(path), f"--set {key}")
    return recipe_from_dict(data, str(path))


def needed_stages(recipe: Recipe, names: set[str]) -> set[str]:
    """``names`` and every stage they read (:meth:`StageSpec.edges`), transitively (references checked by
    :func:`stage_order`)."""
    out: set[str] = set()
    todo = list(names)
    while todo:
        name = todo.pop()
        if name in out:
            continue
        out.add(name)
        todo += list(recipe.stages[name].edges().values())
    return out


def stage_order(recipe: Recipe) -> list[str]:
    """Stage names in dependency order (a teacher stage before its students)."""
    order: list[str] = []
    state: dict[str, int] = {}
    problems: list[tuple[str, str]] = []

    def visit(name: str, path: list[str]) -> None:
        if state.get(name) == 2:
            return
        if state.get(name) == 1:
            problems.append((f"stages.{name}", f"cycle of teacher/init stages: {' -> '.join(path + [name])}"))
            return
        state[name] = 1
        for field_name, upstream in recipe.stages[name].edges().items():
            if upstream not in recipe.stages:
                import difflib

                close = difflib.get_close_matches(upstream, list(recipe.stages), n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                problems.append((f"stages.{name}.{field_name}.from", f"no stage named {upstream!r}{hint}"))
            else:
                visit(upstream, path + [name])
        state[name] = 2
        order.append(name)

    for name in recipe.stages:
        visit(name, [])
    if problems:
        raise RecipeError(problems)
    return order
