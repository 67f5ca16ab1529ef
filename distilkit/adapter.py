"""The adapter contract: how distilkit sees a teacher or student model.

An adapter is an ``nn.Module`` registered in ``distilkit.registry.ADAPTERS``. It declares

* ``Params``: a pydantic model of its constructor parameters (validated when a recipe loads);
* ``INPUTS``: the batch inputs ``forward`` reads (checked against the dataset's fields by ``validate``;
  ``inputs(params)`` when they depend on the parameters);
* ``TAPS``: tap name -> tap kind (see :mod:`distilkit.taps`) that ``forward`` returns;
* ``PREDICTION_TAP``: the tap (of any kind) that evaluation scores, with the metrics registered for its kind;
* ``DEFAULT_TASK_LOSSES``: task losses used when a recipe stage names none;
* ``VERSION``: bump it when the model's behaviour changes, so that stages using it retrain.
* ``NETWORKS``: for each ``size`` the model has ("" when it has none), whether it builds the paper's network or a
  CPU stand-in; ``validate`` and ``distilkit list adapters`` show it (override ``network`` when other fields decide).

The declarations live in :class:`~distilkit.cards.base.AdapterCard` (torch-free, so a recipe is checked without
importing torch); a built-in adapter's card subclasses it and the adapter subclasses its card. ``CAPABILITIES``
names the methods a term may call (``denoise``), so ``validate`` checks them from the card.

``forward(batch)`` takes the collated :class:`~distilkit.data.batch.Batch` (built by the dataset's
registered collate) and returns a dict with (at least) every declared tap. ``check_data`` lets an
adapter reject parameters the data cannot serve (e.g. more frames than it has); ``describe`` gives the
short input description the results table shows; ``tap_grid`` and ``tap_camera`` declare the voxel grid
or camera of a tap (so ``validate`` checks alignments); ``read_weights`` reads a published checkpoint
format (recipes: ``init: {checkpoint: ...}`` and ``teacher: {checkpoint: ...}``).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

from pydantic import BaseModel
from torch import nn

from distilkit.cards.base import AdapterCard, NoParams
from distilkit.data.batch import Batch
from distilkit.data.info import DataInfo


class Adapter(AdapterCard, nn.Module, ABC):
    """A teacher or student model (its declarations are :class:`~distilkit.cards.base.AdapterCard`'s)."""

    def __init__(self, params: BaseModel, info: DataInfo) -> None:
        super().__init__()
        self.params = params
        self.info = info
        self.tap_kinds: dict[str, str] = dict(self.TAPS)  # plus taps a recipe records from submodules

    @abstractmethod
    def forward(self, batch: Batch) -> dict[str, Any]:
        """Run the model on a collated batch; return every declared tap."""

    @classmethod
    def read_weights(cls, path: str) -> dict[str, Any]:
        """The model's weights (a state dict) from a file, loaded safely. Default: a distilkit checkpoint
        (its ``student``), or a file holding a state dict (also under ``state_dict`` or ``model``, as many
        releases do). Override it to convert a model's published checkpoint format to this adapter's names."""
        from distilkit.weights import read_state_dict

        return read_state_dict(path)


__all__ = ["Adapter", "NoParams"]
