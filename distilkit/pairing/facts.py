"""What ``distilkit init`` knows of a model's taps, torch-free: from its adapter's card (kind, voxel grid, camera, the
logits' width) and, once :mod:`distilkit.pairing.probe` has run it on a dry batch, each tap's channels and shape."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class TapFact:
    """One tap of one model: its name, kind, the voxel grid it lives on (None: not on one, or unknown), the camera
    of image features, its channels and its spatial shape on the dry batch (None until probed)."""

    tap: str
    kind: str
    grid: Any = None
    camera: Any = None
    channels: int | None = None
    shape: tuple[int, ...] | None = None
    present: bool = True  # False: declared, but the probed forward did not return it with these parameters
    of: str | None = None  # a bird's-eye map init makes of this voxel tap (a recipe tap: ``of``, ``collapse: max``)

    def size(self) -> str:
        """The grid (``32x32x4``), else the probed shape, else ``?`` (``not returned`` for an absent tap)."""
        if not self.present:
            return "not returned"
        if self.grid is not None:
            return "x".join(map(str, self.grid.shape[:2] if self.kind == "bev_features" else self.grid.shape))
        return "x".join(map(str, self.shape)) if self.shape else "?"


@dataclass
class ModelFacts:
    """A model of the pair: its role (``teacher`` or ``student``), adapter, parameters as given, card, capabilities
    (methods a term may call) and taps in their declaration order."""

    role: str
    adapter: str
    params: dict[str, Any]
    card: Any
    capabilities: frozenset[str]
    taps: list[TapFact] = field(default_factory=list)
    probed: bool = False

    def tap(self, name: str) -> TapFact:
        return next(t for t in self.taps if t.tap == name)

    def of_kind(self, kind: str) -> list[TapFact]:
        """The taps that serve a role reading ``kind`` (the kind or a refinement), in declaration order."""
        from distilkit.taps import kind_fits

        return [t for t in self.taps if t.present and kind_fits(t.kind, kind)]


def card_facts(role: str, model: Any, info: Any, given: dict[str, Any]) -> ModelFacts:
    """A resolved model's taps as its card declares them: kind, grid (``tap_grid``), camera (``tap_camera``); a
    ``voxel_logits`` tap is as wide as the data has classes (that kind's contract)."""
    card, params = model.card, model.params
    taps = []
    for name, kind in {**card.TAPS, **{h: getattr(s, "kind", None) for h, s in model.hooks.items()}}.items():
        if kind is None:
            continue
        grid = card.tap_grid(name, params, info) if name in card.TAPS else None
        camera = card.tap_camera(name, params, info) if name in card.TAPS else None
        channels = info.num_classes if kind == "voxel_logits" else None
        taps.append(TapFact(name, kind, grid, camera, channels))
    return ModelFacts(role, model.adapter, dict(given), card, frozenset(card.CAPABILITIES), taps)


BEV_OF = ("sparse_features", "volume_features")


def with_bev(facts: ModelFacts) -> ModelFacts:
    """``facts`` and, for each voxel feature tap on a known grid, the bird's-eye map a recipe tap makes of it
    (``bev_<tap>``: the tap collapsed over height by max, as wide, on the grid's (X, Y) plane)."""
    made = [TapFact(f"bev_{t.tap}", "bev_features", t.grid, channels=t.channels,
                    shape=tuple(t.shape[:2]) if t.shape else None, of=t.tap)
            for t in facts.taps if t.kind in BEV_OF and t.grid is not None and t.present]
    names = {t.tap for t in facts.taps}
    return dataclasses.replace(facts, taps=facts.taps + [t for t in made if t.tap not in names])


def with_probe(facts: ModelFacts, probed: dict[str, tuple[int | None, tuple[int, ...] | None]]) -> ModelFacts:
    """``facts`` with each probed tap's channels and shape (``probed``: tap -> (channels, shape)); a declared tap
    the forward did not return is marked absent (an adapter may return some taps only with some parameters)."""
    taps = [dataclasses.replace(t, channels=probed[t.tap][0] if probed[t.tap][0] is not None else t.channels,
                                shape=probed[t.tap][1]) if t.tap in probed else dataclasses.replace(t, present=False)
            for t in facts.taps]
    return dataclasses.replace(facts, taps=taps, probed=True)


__all__ = ["BEV_OF", "ModelFacts", "TapFact", "card_facts", "with_bev", "with_probe"]
