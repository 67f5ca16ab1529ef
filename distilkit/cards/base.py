"""The contracts' declarations, torch-free: what an adapter, a term (task loss or distillation objective) and a
metric declare about themselves. :class:`distilkit.adapter.Adapter`, :class:`distilkit.term.Term` and
:class:`distilkit.metrics.base.Metric` add the computing part; a built-in component's card subclasses one of these
and its implementation subclasses the card (see ``distilkit.cards``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from pydantic import BaseModel

from distilkit.registry import NoParams

if TYPE_CHECKING:
    from distilkit.data.info import Camera, DataInfo
    from distilkit.structures import VoxelGrid


class AdapterCard:
    """What an adapter declares (the contract is :mod:`distilkit.adapter`'s docstring): ``Params``, ``INPUTS``,
    ``TAPS``, ``PREDICTION_TAP``, ``DEFAULT_TASK_LOSSES``, ``VERSION``, ``NETWORKS``, the teacher or student
    ``CAPABILITIES`` a term may call (``denoise``: methods of the implementation, declared here so that ``validate``
    checks them without building it), and the class methods ``validate`` calls."""

    Params: ClassVar[type[BaseModel]] = NoParams
    INPUTS: ClassVar[frozenset[str]] = frozenset()
    TAPS: ClassVar[dict[str, str]] = {}
    PREDICTION_TAP: ClassVar[str] = "logits"
    DEFAULT_TASK_LOSSES: ClassVar[list[dict[str, Any]]] = [{"name": "ce", "weight": 1.0}]
    VERSION: ClassVar[int] = 1
    NETWORKS: ClassVar[dict[str, str]] = {}  # by ``params.size`` ("" without one): the paper's network or a stand-in
    CAPABILITIES: ClassVar[frozenset[str]] = frozenset()  # methods a term may call through its context
    # an input only an auxiliary model's tap provides -> the adapter whose prediction it is (``distilkit init`` adds
    # that stage; e.g. VoxFormer's ``proposal``: voxformer-proposal)
    AUX_INPUTS: ClassVar[dict[str, str]] = {}
    DATA_PARAMS: ClassVar[dict[str, Any]] = {}  # data parameters the adapter needs (VoxFormer: ``camera: {}``)

    @classmethod
    def inputs(cls, params: BaseModel) -> frozenset[str]:
        """The batch fields ``forward`` reads with these parameters (default: ``INPUTS``); ``validate`` checks the
        data provides them, and a stage's identity follows the versions of the fields it reads."""
        return cls.INPUTS

    @classmethod
    def tap_grid(cls, tap: str, params: BaseModel, info: DataInfo) -> VoxelGrid | None:
        """The voxel grid (geometry: origin, voxel size, shape) a voxel tap lives on, known before training
        (default: the data's SSC grid); None for taps that are not on a voxel grid. ``validate`` checks
        alignments with it."""
        if info.grid is not None and cls.TAPS.get(tap) in ("sparse_features", "voxel_logits"):
            return info.grid
        return None

    @classmethod
    def tap_camera(cls, tap: str, params: BaseModel, info: DataInfo) -> Camera | None:
        """The camera an ``image_features`` tap sees through (default: the data's camera when it has one);
        ``validate`` refuses to pair image features of different cameras."""
        if cls.TAPS.get(tap) == "image_features" and len(info.cameras) == 1:
            return info.cameras[0]
        return None

    @classmethod
    def check_data(cls, params: BaseModel, info: DataInfo) -> list[tuple[str, str]]:
        """(parameter, problem) pairs for parameters this data cannot serve (default: none)."""
        return []

    @classmethod
    def network(cls, params: BaseModel) -> str:
        """What these parameters build — the paper's network or a CPU stand-in — for ``validate`` and ``list
        adapters`` (default: ``NETWORKS`` at ``params.size``, or at "" for an adapter without sizes)."""
        return cls.NETWORKS.get(str(getattr(params, "size", "")), "")

    @classmethod
    def describe(cls, params: BaseModel) -> str:
        """A short description of the model's input for the results table (default: empty)."""
        return ""

    @classmethod
    def sparse(cls, params: BaseModel) -> bool | None:
        """Whether the network these parameters build holds sparse convolutions (``validate`` then checks that the
        sparse backend can run them); None: not declared, so ``validate`` builds the model on the meta device to
        see (which imports torch). A built-in adapter declares it, tested against the built model."""
        return None

    @classmethod
    def taps_of_kind(cls, kind: str) -> list[str]:
        from distilkit.taps import kind_fits

        return [name for name, k in cls.TAPS.items() if kind_fits(k, kind)]


CHANNELS = ("equal", "any", "own")
SPATIAL = ("same", "aligned", "resampled", "collapsed")


@dataclass(frozen=True)
class Match:
    """How a teacher role's tap must match its student partner's (the student role of the same suffix:
    ``teacher_logits`` pairs with ``student_logits``), for ``distilkit init`` and the objectives page; each built-in
    declaration is tested against its loss (tests/test_objective_match.py).

    ``channels``: ``equal`` (compared channel by channel: a connector on the ``student`` role makes the widths
    equal; on another role they must be), ``any`` (each side keeps its width), ``own`` (the term projects the
    student itself: its default connector or a head of its own). ``spatial``: ``same`` (one voxel grid, or maps of
    one size), ``aligned`` (voxel grids in an integer ratio, matched voxel by voxel across them), ``resampled`` (any
    sizes of one dimensionality: the term resizes), ``collapsed`` (the teacher's voxel grid, its height collapsed,
    is the student's bird's-eye plane). ``on_labels``: the maps' size must divide the labels' grid (the term masks
    them by the labels pooled to their size)."""

    channels: Literal["equal", "any", "own"]
    spatial: Literal["same", "aligned", "resampled", "collapsed"]
    on_labels: bool = False

    def __post_init__(self) -> None:
        if self.channels not in CHANNELS or self.spatial not in SPATIAL:
            raise ValueError(f"Match: channels must be one of {CHANNELS} and spatial one of {SPATIAL}, got "
                             f"{self.channels!r} and {self.spatial!r}")

    def text(self) -> str:
        """``channels · spatial`` (``, on the labels' grid``), as the objectives page shows it."""
        return f"{self.channels} · {self.spatial}" + (" (divides the labels' grid)" if self.on_labels else "")


def partner(role: str) -> str:
    """The student role a teacher role pairs with: the one of the same suffix (``teacher_2``: ``student_2``)."""
    return "student" + role[len("teacher"):]


class TermCard:
    """What a term declares (the contract is :mod:`distilkit.term`'s docstring): its parameters, roles and where
    each comes from, the capabilities it calls, its default weight, connector and parameter groups, its version."""

    Params: ClassVar[type[BaseModel]]
    CONSUMES: ClassVar[dict[str, str]] = {}  # role -> tap kind (student's, or the teacher's for TEACHER_ROLES)
    TEACHER_ROLES: ClassVar[frozenset[str]] = frozenset()
    OPTIONAL: ClassVar[frozenset[str]] = frozenset()  # tap roles used only when the recipe names a tap
    # role -> the batch field read for it, or candidates in order of preference (the first the data provides)
    BATCH: ClassVar[dict[str, str | tuple[str, ...]]] = {}
    BATCH_HINTS: ClassVar[dict[str, str]] = {}  # role -> what to do when the data lacks its field (validate says it)
    REQUIRES: ClassVar[frozenset[str]] = frozenset()  # teacher capabilities called through the context
    STUDENT_REQUIRES: ClassVar[frozenset[str]] = frozenset()  # student capabilities called through the context
    DEFAULT_WEIGHT: ClassVar[float] = 1.0
    DEFAULT_CONNECTOR: ClassVar[str | None] = None  # e.g. "linear": the student tap is projected first
    DEFAULT_PARAM_GROUPS: ClassVar[list[dict[str, Any]]] = []  # optimizer groups asked for by default
    VERSION: ClassVar[int] = 1  # bump when the term's numbers change: stages using it retrain
    # teacher role -> how its tap must match the student partner's; {} for a term that declares none (a plug-in's:
    # then the first step decides) or reads no teacher tap
    MATCH: ClassVar[dict[str, Match]] = {}
    # role -> the tap names it prefers, in order, where a model has several taps of its kind (``distilkit init``)
    TAP_HINTS: ClassVar[dict[str, tuple[str, ...]]] = {}

    @classmethod
    def match(cls, params: BaseModel | None = None) -> dict[str, Match]:
        """How each teacher role's tap must match its partner's with these parameters (default: ``MATCH``; None:
        the defaults)."""
        return cls.MATCH

    @classmethod
    def roles(cls) -> dict[str, str]:
        """Every role and its source: ``student``, ``teacher`` or ``batch``."""
        out = {role: "teacher" if role in cls.TEACHER_ROLES else "student" for role in cls.CONSUMES}
        return {**out, **{role: "batch" for role in cls.BATCH}}

    @classmethod
    def default_field(cls, role: str, fields: frozenset[str] | set[str]) -> str:
        """The batch field a batch role reads unless a recipe names another: the first of its candidates that
        ``fields`` holds (the first one when none does, or when ``fields`` is unknown)."""
        default = cls.BATCH[role]
        candidates = (default,) if isinstance(default, str) else tuple(default)
        return next((c for c in candidates if c in fields), candidates[0])

    @classmethod
    def student_requires(cls, params: BaseModel) -> frozenset[str]:
        """The student capabilities this term calls with these parameters (default: ``STUDENT_REQUIRES``)."""
        return cls.STUDENT_REQUIRES

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        """For each teacher role on a voxel grid, the voxels whose teacher values can change this term's value or
        gradient with these parameters: ``all``, ``valid`` (label != ignore) or ``occupied`` (valid and not empty),
        chosen by the term's ``target`` labels (default: ``all`` for every teacher role). A teacher store with
        ``voxels: valid`` or ``occupied`` keeps only those voxels, and ``validate`` refuses it for a term that reads
        more."""
        return {role: "all" for role in cls.TEACHER_ROLES}

    @classmethod
    def teacher_softmax(cls, params: BaseModel) -> frozenset[str]:
        """The teacher roles whose class scores this term reads only through a softmax over the classes (at any
        temperature), so that a store of the top-k scores with the remaining probability mass is an
        approximation it can read (default: none: the term needs every class's score, and ``validate`` refuses a
        top-k store for it)."""
        return frozenset()


class ObjectiveCard(TermCard):
    """A distillation objective's declarations: its ``teacher`` role reads the teacher (see
    :class:`distilkit.objectives.base.Objective`)."""

    TEACHER_ROLES: ClassVar[frozenset[str]] = frozenset({"teacher"})


class MetricCard:
    """What a metric declares (the contract is :mod:`distilkit.metrics.base`'s docstring): the prediction kind it
    scores, the targets it reads, its keys and how reports show them."""

    SCORES: ClassVar[str]
    TARGETS: ClassVar[frozenset[str]] = frozenset()
    KEYS: ClassVar[tuple[str, ...]] = ()
    LOWER_IS_BETTER: ClassVar[frozenset[str]] = frozenset()
    SELECTS: ClassVar[str] = ""  # the score that picks best.pt when a recipe names none ("": never by default)
    # how reports show the scores: a title, (key, header, scale) columns (default: every key as it is),
    # and a per-class list with the train id of its first entry
    TITLE: ClassVar[str] = ""
    COLUMNS: ClassVar[tuple[tuple[str, str, float], ...]] = ()
    PER_CLASS: ClassVar[tuple[str, str, float] | None] = None  # (key of a per-class list, header, scale)
    PER_CLASS_FROM: ClassVar[int] = 0

    @classmethod
    def columns(cls) -> tuple[tuple[str, str, float], ...]:
        return cls.COLUMNS or tuple((k, k, 1.0) for k in cls.KEYS)




def declare_objective(name: str, impl: str, card: type[TermCard], *, description: str, paper: str, equation: str,
                      shapes: str, function: str | None = None) -> None:
    """Declare the objective ``name`` (implementation ``impl``, "module:attr", imported when it runs) with its card;
    the same metadata as :func:`distilkit.objectives.base.register_objective` (tap kinds and default weight read from
    the card; ``function``: the plain function of ``distilkit.losses`` that computes its maths, default ``name``)."""
    from distilkit.registry import OBJECTIVES

    kinds = tuple(dict.fromkeys(card.CONSUMES.values()))
    OBJECTIVES.declare(name, impl, card=card, description=description, paper=paper, consumes=kinds,
                       default_weight=card.DEFAULT_WEIGHT, equation=equation, shapes=shapes,
                       function=f"distilkit.losses.{function or name}")


__all__ = ["AdapterCard", "Match", "MetricCard", "NoParams", "ObjectiveCard", "TermCard", "declare_objective", "partner"]
