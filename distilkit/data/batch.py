"""The collated batch every adapter, task loss, objective and metric receives.

``inputs`` are what a model may read (points, images, ...), ``targets`` what losses and metrics read
(labels, masks), ``meta`` the rest (``size``: the number of samples; calibration, ids). Each dataset
registers the collate that builds it; adapters declare the inputs they read (``Adapter.INPUTS``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where a batch is built or moved, not to name the batch's fields
    import torch
    from torch import Tensor


@dataclass
class Batch:
    inputs: dict[str, Tensor]
    targets: dict[str, Tensor] = field(default_factory=dict)
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def size(self) -> int:
        """Number of samples."""
        return int(self.meta["size"])

    def to(self, device: torch.device) -> "Batch":
        from torch import Tensor

        def move(d: dict[str, Any]) -> dict[str, Any]:
            return {k: v.to(device, non_blocking=True) if isinstance(v, Tensor) else v for k, v in d.items()}

        return Batch(move(self.inputs), move(self.targets), move(self.meta))

    def field(self, name: str) -> Any:
        """A field by name from targets, inputs or meta (a term's ``batch`` source)."""
        for part in (self.targets, self.inputs, self.meta):
            if name in part:
                return part[name]
        raise KeyError(f"the batch has no field {name!r} (inputs: {', '.join(self.inputs) or '—'}; "
                       f"targets: {', '.join(self.targets) or '—'}; meta: {', '.join(self.meta) or '—'})")

    def with_inputs(self, **inputs: Tensor) -> "Batch":
        """A copy with some inputs replaced (e.g. fewer frames); targets and meta are shared."""
        return replace(self, inputs={**self.inputs, **inputs})

    @property
    def fields(self) -> frozenset[str]:
        return frozenset(self.inputs) | frozenset(self.targets)
