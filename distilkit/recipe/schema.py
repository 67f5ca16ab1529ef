"""The recipe schema (pydantic v2): the single source of truth for configuration — a recipe's data, its stages (model,
teacher, initial weights, labels, auxiliary models, task losses, distillation terms, optimizer, training) and its
report. A component's own parameters are validated against its registered model later, by
:func:`distilkit.engine.assemble.resolve.resolve`."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from distilkit.recipe.augment import AugmentSpec
from distilkit.recipe.hook_taps import HookTapSpec
from distilkit.recipe.store import StoreSpec

SCHEMA_VERSION = 1
MAX_NAME = 128  # recipe and stage names name folders (<stage>-<hash>: within the 255 bytes a file name may have)
MAX_LABEL = 200  # what reports show of a stage
MAX_NOTE = 1000


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", populate_by_name=True)


class ModelSpec(_Strict):
    """A model: a registered adapter and its parameters."""

    adapter: str = Field(..., description="registered adapter name (see `distilkit list`)")
    params: dict[str, Any] = Field(default_factory=dict, description="the adapter's parameters")
    taps: dict[str, HookTapSpec] = Field(default_factory=dict,
                                         description="extra taps recorded from submodules by forward hooks")


class EmaSpec(_Strict):
    """A stage that is its own teacher: an exponential moving average of its student (HASSC's mean teacher).

    A copy of the student at step 0; before the forward of step k (0-based) — i.e. after optimiser step k − 1 —
    t ← m·t + (1 − m)·s with m = min(1 − 1/(k + 1), ``momentum``), without gradients (HASSC's
    ``SelfDistillTeacherOcc.momentum_update``, called at the start of every ``forward_train``)."""

    momentum: float = Field(0.99, ge=0, lt=1, description="the largest momentum m (HASSC 0.99); m = min(1 - 1/(k+1), "
                                                          "momentum) at step k")
    buffers: Literal["average", "copy_once"] = Field(
        "average", description="average: buffers (BatchNorm statistics) averaged like the parameters, integer ones "
                               "copied (default: an eval-mode teacher then uses statistics of the weights it has); "
                               "copy_once: copied at step 0 only, parameters averaged (the HASSC release)")
    mode: Literal["eval", "train"] = Field(
        "eval", description="eval: the teacher runs in eval mode (the paper; the release asks for it); train: "
                            "dropout and batch statistics on (what the release's teacher does in fact: mmcv's "
                            "runner calls model.train() on the detector, the teacher being its submodule)")


class TeacherSpec(_Strict):
    """Where a stage's frozen teacher comes from: an earlier stage, a checkpoint file, or the stage's own student
    (``ema``: a moving average of it, updated as it trains)."""

    from_: str | None = Field(None, alias="from", description="name of an earlier stage whose best model is the teacher")
    checkpoint: str | None = Field(None, description="path of a distilkit checkpoint (loaded with weights_only=True)")
    model: ModelSpec | None = Field(None, description="the teacher's model (required with `checkpoint`)")
    which: Literal["best", "last"] = Field("best", description="checkpoint of the upstream stage to use")
    ema: EmaSpec | None = Field(None, description="the student's exponential moving average is the teacher (HASSC): "
                                                  "`ema: true` or its settings")
    mode: Literal["eval", "train"] = Field(
        "eval", description="the frozen teacher's module mode (no gradients either way): eval (default: BatchNorm's "
                            "running statistics, no dropout); train: batch statistics, dropout and drop-path on, and "
                            "BatchNorm's running statistics updated by every teacher forward as PyTorch does under "
                            "no_grad (kept in last.pt, so a resumed run goes on with them) — what the L2COcc and "
                            "HASSC releases do (their frameworks call .train() on the module holding the teacher). "
                            "With `ema`, the same as `ema.mode`")
    taps: dict[str, HookTapSpec] = Field(default_factory=dict,
                                         description="extra teacher taps recorded from submodules by forward hooks")
    control: Literal["random", "shuffled"] | None = Field(
        None, description="a control for distillation itself (arXiv 2510.12615): random = the architecture with random "
                          "weights (from the stage's seed); shuffled = the real teacher's outputs for another training "
                          "sample (a fixed random cycle from the stage's seed, the same augmentation draw)")
    store: StoreSpec | None = Field(None, description="run the frozen teacher once over the training split (under "
                                                      "every transform of train.augment) and read its outputs from "
                                                      "disk: `store: true` or its settings; students that share the "
                                                      "teacher, data, taps and augmentation share one store")

    @field_validator("store", mode="before")
    @classmethod
    def _store_shorthand(cls, value: Any) -> Any:
        return {} if value is True else None if value is False else value

    @field_validator("ema", mode="before")
    @classmethod
    def _ema_shorthand(cls, value: Any) -> Any:
        return {} if value is True else None if value is False else value

    @model_validator(mode="after")
    def _one_source(self) -> "TeacherSpec":
        sources = [n for n, v in (("from", self.from_), ("checkpoint", self.checkpoint), ("ema", self.ema))
                   if v is not None]
        if len(sources) != 1:
            raise ValueError("give exactly one of `from` (an earlier stage), `checkpoint` (a file) or `ema` (the "
                             f"student's moving average){'; got ' + ', '.join(sources) if sources else ''}")
        if self.checkpoint is not None and self.model is None:
            raise ValueError("a `checkpoint` teacher needs `model` (adapter and params)")
        if self.control is not None and (self.ema is not None or (self.control == "random" and self.store)):
            raise ValueError(f"`control: {self.control}` with `{'ema' if self.ema else 'store'}`: a control needs a "
                             "teacher of its own (not the student's average), and a random one runs live (no store)")
        if self.ema is not None and self.model is not None:
            raise ValueError("an `ema` teacher is the student's own model: leave out `model`")
        if self.ema is not None:  # one mode, either spelling: `mode` and `ema.mode` agree (and hash alike)
            if "mode" in self.model_fields_set and "mode" in self.ema.model_fields_set and self.mode != self.ema.mode:
                raise ValueError(f"`mode: {self.mode}` and `ema.mode: {self.ema.mode}` disagree: give one")
            self.mode = self.ema.mode = self.mode if "mode" in self.model_fields_set else self.ema.mode
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
                          "registered connector (linear, mlp, conv3; height_max or height_mean: voxel features "
                          "collapsed over height onto the bird's-eye plane, then 1x1; or a plugin's: `distilkit list "
                          "connectors`) or none (default: the objective's own; fitnets: linear)")
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
    augment: AugmentSpec | None = Field(None, description="training samples under a random transform, every field "
                                                          "alike, drawn per sample and step from the seed: flips and "
                                                          "quarter turns (JS3C-Net: {flip: [x, y], rotate90: z}) or, "
                                                          "for point clouds, LiDiff's turn, tilt and scale; none by "
                                                          "default")

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
    threads: int | None = Field(None, ge=1, le=4096, description="CPU threads each process computes with "
                                "(torch.set_num_threads); default: OMP_NUM_THREADS, else Slurm's SLURM_CPUS_PER_TASK, "
                                "else the CPUs of the process's affinity mask; on the command line --threads N. Not "
                                "part of any stage's identity (each stage's summary records the count)")
    data: DataSpec = Field(default_factory=DataSpec)
    stages: dict[str, StageSpec] = Field(..., min_length=1)
    report: ReportSpec = Field(default_factory=ReportSpec)
    trackers: list[str | dict[str, dict[str, Any] | None]] = Field(
        default_factory=list, description="experiment trackers every stage logs to (registered hooks: tensorboard, "
                                          "wandb, mlflow, trackio, or a plugin's; each one's parameters: Trackers "
                                          "in docs/reference/recipe.md), each once, as a name or {NAME: {param: "
                                          "value}}, e.g. [tensorboard, {wandb: {project: kd, mode: offline}}]; on the "
                                          "command line --set 'trackers=[mlflow]'. Not part of any stage's identity")

    @field_validator("trackers")
    @classmethod
    def _trackers(cls, v: list[Any]) -> list[Any]:
        seen: dict[str, int] = {}
        for i, item in enumerate(v):
            if isinstance(item, dict) and len(item) != 1:
                raise ValueError(f"trackers[{i}]: give one tracker per entry, as NAME or {{NAME: {{params}}}}, got "
                                 f"{len(item)} names ({', '.join(map(str, item)) or 'none'})")
            name = item if isinstance(item, str) else next(iter(item))
            if name in seen:  # one run per tracker and stage: a second entry would log into the first's run
                raise ValueError(f"trackers[{i}]: {name} is given twice (trackers[{seen[name]}] and trackers[{i}]); "
                                 "give each tracker once, with all its parameters")
            seen[name] = i
        return v

    def tracker_specs(self) -> list[tuple[str, dict[str, Any]]]:
        """``trackers`` as (name, params) pairs."""
        pairs = [(item, None) if isinstance(item, str) else next(iter(item.items())) for item in self.trackers]
        return [(name, params or {}) for name, params in pairs]

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
