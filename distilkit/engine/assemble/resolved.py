"""What a resolved recipe is: each stage's models, terms, metrics, hooks and auxiliary models with their registered
classes and validated parameters (:func:`~distilkit.engine.assemble.resolve.resolve` builds it from a recipe; the
trainer, the identities and the memory estimate read it)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel

from distilkit.recipe import Recipe


@dataclass
class ResolvedTerm:
    name: str
    card: Any  # what the term declares (:class:`~distilkit.cards.base.TermCard`); ``cls`` is the term itself
    params: BaseModel
    weight: float
    taps: dict[str, str]  # role -> tap name (of the student, or of the teacher for a teacher role)
    connector: str | None = None  # projection of the student tap to the teacher's channels
    fields: dict[str, str] = field(default_factory=dict)  # role -> batch field
    key: str = ""  # unique within its list: the name, then name_2, name_3 for repeats (logs, parameter names)
    warmup_steps: int = 0  # the weight grows linearly over the first N steps

    def __post_init__(self) -> None:
        self.key = self.key or self.name

    @property
    def cls(self) -> Any:
        """The component itself (imported now if it was declared lazily): what builds and runs it."""
        from distilkit.registry import implementation

        return implementation(self.card)


@dataclass
class ResolvedModel:
    adapter: str
    card: Any  # what the adapter declares (:class:`~distilkit.cards.base.AdapterCard`); ``cls`` is the adapter
    params: BaseModel
    hooks: dict[str, Any] = field(default_factory=dict)  # recipe taps recorded from submodules

    @property
    def cls(self) -> Any:
        """The component itself (imported now if it was declared lazily): what builds and runs it."""
        from distilkit.registry import implementation

        return implementation(self.card)

    @property
    def taps(self) -> dict[str, str]:
        """Tap name -> kind: the adapter's declared taps and the recipe's recorded ones."""
        return {**self.card.TAPS, **{name: h.kind for name, h in self.hooks.items() if name not in self.card.TAPS}}


@dataclass
class ResolvedMetric:
    """The registered metric that scores a stage's predictions and the score that selects ``best.pt``."""

    name: str
    card: Any  # what the metric declares (:class:`~distilkit.cards.base.MetricCard`); ``cls`` is the metric
    key: str

    @property
    def higher_is_better(self) -> bool:
        return self.key not in self.card.LOWER_IS_BETTER

    @property
    def cls(self) -> Any:
        """The component itself (imported now if it was declared lazily): what builds and runs it."""
        from distilkit.registry import implementation

        return implementation(self.card)


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

    @property
    def ema(self) -> Any:
        """The settings of the stage's own moving-average teacher (``teacher: {ema: ...}``), else None."""
        return self.spec.teacher.ema if self.spec.teacher is not None else None


@dataclass
class ResolvedRecipe:
    recipe: Recipe
    data_params: BaseModel
    data_info: Any
    stages: dict[str, ResolvedStage]
    order: list[str]

    def has_split(self, split: str) -> bool:
        """Whether the data has ``split`` (the dataset's registered ``has_split``; by default every split but test)."""
        from distilkit.registry import DATASETS

        has = DATASETS.entry(self.recipe.data.dataset).meta.get("has_split", lambda params, s: s != "test")
        return bool(has(self.data_params, split))

