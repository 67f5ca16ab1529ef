"""Each built-in objective's ``match()`` (how a teacher role's tap must match its student partner's: channels,
spatial, the labels' grid; what ``distilkit init`` pairs by) against the objective itself, on hand-made taps in
float64: a teacher one channel wider raises iff the declaration says ``equal``; a teacher of another size raises iff
it says ``same`` (``aligned``: an integer ratio passes, another does not; ``resampled``: any size passes;
``collapsed``: the teacher's grid must collapse to the student's plane); maps whose size does not divide the labels'
grid raise iff ``on_labels``."""

from __future__ import annotations

import pytest
import torch

import distilkit.cards  # noqa: F401  (declares the built-in objectives)
from distilkit.cards.base import Match, partner
from distilkit.data.batch import Batch
from distilkit.registry import OBJECTIVES
from distilkit.structures import SparseVoxels

D = torch.float64
K = 20  # an unbound term's number of classes (distilkit.term's default)
GRID = (8, 8, 4)  # the labels' grid
C = 4
# (objective, params): every objective reading a teacher tap, and the variants whose match() differs
CASES = [(n, {}) for n in OBJECTIVES.names() if OBJECTIVES.card(n).TEACHER_ROLES] + [
    ("licrocc_affinity", {"size": None}), ("bev_from_voxels", {"adapter": "none"}),
    ("bev_from_voxels", {"weighting": "none"})]
IMAGE = (6, 20)


def _g() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def value(kind: str, channels: int, spatial: tuple[int, ...] | None, g: torch.Generator, image: bool) -> object:
    """A tap value of ``kind`` with ``channels`` channels on ``spatial`` (the voxel grid; a plane takes its (X, Y))."""
    spatial = spatial or GRID
    if kind == "sparse_features":
        coords = torch.cartesian_prod(torch.zeros(1, dtype=torch.long), *[torch.arange(n) for n in spatial])
        coords = coords[torch.rand(len(coords), generator=g) < 0.5]
        return SparseVoxels(coords, torch.randn(len(coords), channels, dtype=D, generator=g), tuple(spatial))
    if kind == "bev_features":
        return torch.randn(1, channels, *spatial[:2], dtype=D, generator=g)
    if kind == "image_features" or (kind == "feature_map" and image):
        return torch.randn(1, channels, *(IMAGE if spatial == GRID else spatial[:2]), dtype=D, generator=g)
    return torch.randn(1, channels, *spatial, dtype=D, generator=g)  # voxel_logits, volume_features, feature_map


def run(name: str, params: dict, role: str, *, channels: int = 0, teacher: tuple[int, ...] | None = None,
        both: tuple[int, ...] | None = None) -> torch.Tensor:
    """The objective's value on taps of ``C`` channels (logits: ``K``) on ``GRID`` for every required role and
    ``role`` with its partner; the teacher ``role`` ``channels`` wider and on ``teacher``; both on ``both``."""
    cls = OBJECTIVES.get(name)
    card = OBJECTIVES.card(name)
    obj = cls(card.Params(**params))
    g = _g()
    target = torch.randint(0, K, GRID, generator=g)[None]
    target[torch.rand(1, *GRID, generator=g) < 0.1] = 255
    batch = Batch({}, {"voxel_target": target, "scribble": target.clone()}, {"size": 1})
    pair = {role, partner(role)}
    image = name == "monoocc_image"
    taps = {}
    for r, kind in card.CONSUMES.items():
        if r in card.OPTIONAL and r not in pair:
            continue
        width = K if kind == "voxel_logits" else C
        spatial = both if r in pair and both is not None else None
        if r == role:
            width, spatial = width + channels, teacher or spatial
        taps[r] = value(kind, width, spatial, g, image)
    taps.update(obj.batch_roles(batch))
    if hasattr(obj, "class_weight"):  # bev_from_voxels' weights, prepared from a training split in a run
        obj.class_weight = torch.ones(K, dtype=D)
    obj.setup(taps, batch)
    obj.double()
    out = obj.compute(taps, batch)
    assert torch.isfinite(out).all()
    return out


def declared(name: str, params: dict) -> dict[str, Match]:
    card = OBJECTIVES.card(name)
    return card.match(card.Params(**params))


def test_every_objective_reading_a_teacher_declares_each_teacher_role() -> None:
    for name in OBJECTIVES.names():
        card = OBJECTIVES.card(name)
        assert set(card.match()) == set(card.TEACHER_ROLES), name
        assert all(partner(r) in card.CONSUMES for r in card.TEACHER_ROLES), name
    with pytest.raises(ValueError, match="channels must be one of"):
        Match("same", "equal")  # type: ignore[arg-type]


CHECKS = [(n, p, r) for n, p in CASES for r in declared(n, p)]
IDS = [f"{n}-{'-'.join(f'{k}={v}' for k, v in p.items()) or 'default'}-{r}" for n, p, r in CHECKS]


@pytest.mark.parametrize("name,params,role", CHECKS, ids=IDS)
def test_the_declared_channels_hold(name, params, role) -> None:
    m = declared(name, params)[role]
    run(name, params, role)  # equal widths: runs
    if m.channels == "equal":
        with pytest.raises(Exception):
            run(name, params, role, channels=1)
    elif m.channels == "any":
        run(name, params, role, channels=1)
    else:  # "own": the card's default connector projects the student, or the term builds its own projection
        card = OBJECTIVES.card(name)
        if card.DEFAULT_CONNECTOR is None:
            run(name, params, role, channels=1)


@pytest.mark.parametrize("name,params,role", CHECKS, ids=IDS)
def test_the_declared_spatial_rule_holds(name, params, role) -> None:
    m = declared(name, params)[role]
    half, odd = (4, 4, 2), (6, 6, 4)  # an integer ratio to GRID, and another
    if m.spatial == "same":
        for size in (half, odd):
            with pytest.raises(Exception):
                run(name, params, role, teacher=size)
    elif m.spatial == "aligned":
        run(name, params, role, teacher=half)
        with pytest.raises(Exception):
            run(name, params, role, teacher=odd)
    elif m.spatial == "resampled":
        run(name, params, role, teacher=half)
        run(name, params, role, teacher=odd)
    else:  # collapsed: the teacher's grid collapses to the student's plane, which GRID's (X, Y) is
        with pytest.raises(Exception):
            run(name, params, role, teacher=half)


@pytest.mark.parametrize("name,params,role", CHECKS, ids=IDS)
def test_the_declared_label_grid_rule_holds(name, params, role) -> None:
    m = declared(name, params)[role]
    divides, not_dividing = (4, 4, 2), (3, 3, 4)
    if OBJECTIVES.card(name).CONSUMES[role] == "voxel_logits":  # logits live on the labels' grid (the kind's rule)
        assert not m.on_labels
    elif m.spatial in ("collapsed", "same"):
        run(name, params, role, both=divides)
        if m.on_labels:
            with pytest.raises(Exception):
                run(name, params, role, both=not_dividing)
        else:
            run(name, params, role, both=not_dividing)
    else:
        assert not m.on_labels  # a rule on the labels' grid only for maps compared cell by cell


def test_tap_hints_name_taps_some_adapter_declares_with_the_roles_kind() -> None:
    from distilkit.registry import ADAPTERS
    from distilkit.taps import kind_fits

    declared = {(tap, kind) for name in ADAPTERS.names() for tap, kind in ADAPTERS.card(name).TAPS.items()}
    for name in OBJECTIVES.names():
        card = OBJECTIVES.card(name)
        for role, taps in card.TAP_HINTS.items():
            assert role in card.CONSUMES, (name, role)
            for tap in taps:
                assert any(t == tap and kind_fits(k, card.CONSUMES[role]) for t, k in declared), (name, role, tap)
