"""The adapter contract: how distilkit sees a teacher or student model.

An adapter is an ``nn.Module`` registered in :data:`distilkit.registry.ADAPTERS`. It declares

* ``Params``: a pydantic model of its constructor parameters (validated when a recipe loads);
* ``INPUTS``: the batch inputs ``forward`` reads (checked against the dataset's fields by ``validate``;
  ``inputs(params)`` when they depend on the parameters);
* ``TAPS``: tap name -> tap kind (see :mod:`distilkit.taps`) that ``forward`` returns;
* ``PREDICTION_TAP``: the tap (of any kind) that evaluation scores, with the metrics registered for its kind;
* ``DEFAULT_TASK_LOSSES``: task losses used when a recipe stage names none;
* ``VERSION``: bump it when the model's behaviour changes, so that stages using it retrain.
* ``NETWORKS``: for each ``size`` the model has ("" when it has none), whether it builds the paper's network or a
  CPU stand-in; ``validate`` and ``distilkit list adapters`` show it (override ``network`` when other fields decide).

``forward(batch)`` takes the collated :class:`~distilkit.data.batch.Batch` (built by the dataset's
registered collate) and returns a dict with (at least) every declared tap. ``check_data`` lets an
adapter reject parameters the data cannot serve (e.g. more frames than it has); ``describe`` gives the
short input description the results table shows; ``tap_grid`` and ``tap_camera`` declare the voxel grid
or camera of a tap (so ``validate`` checks alignments); ``read_weights`` reads a published checkpoint
format (recipes: ``init: {checkpoint: ...}`` and ``teacher: {checkpoint: ...}``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict
from torch import nn

from distilkit.data.batch import Batch
from distilkit.data.info import Camera, DataInfo
from distilkit.structures import VoxelGrid


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Adapter(nn.Module, ABC):
    Params: ClassVar[type[BaseModel]] = NoParams
    INPUTS: ClassVar[frozenset[str]] = frozenset()
    TAPS: ClassVar[dict[str, str]] = {}
    PREDICTION_TAP: ClassVar[str] = "logits"
    DEFAULT_TASK_LOSSES: ClassVar[list[dict[str, Any]]] = [{"name": "ce", "weight": 1.0}]
    VERSION: ClassVar[int] = 1
    NETWORKS: ClassVar[dict[str, str]] = {}  # by ``params.size`` ("" without one): the paper's network or a stand-in

    def __init__(self, params: BaseModel, info: DataInfo) -> None:
        super().__init__()
        self.params = params
        self.info = info
        self.tap_kinds: dict[str, str] = dict(self.TAPS)  # plus taps a recipe records from submodules

    @abstractmethod
    def forward(self, batch: Batch) -> dict[str, Any]:
        """Run the model on a collated batch; return every declared tap."""

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
    def read_weights(cls, path: str) -> dict[str, Any]:
        """The model's weights (a state dict) from a file, loaded safely. Default: a distilkit checkpoint
        (its ``student``), or a file holding a state dict (also under ``state_dict`` or ``model``, as many
        releases do). Override it to convert a model's published checkpoint format to this adapter's names."""
        from distilkit.weights import read_state_dict

        return read_state_dict(path)

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
    def taps_of_kind(cls, kind: str) -> list[str]:
        from distilkit.taps import kind_fits

        return [name for name, k in cls.TAPS.items() if kind_fits(k, kind)]
