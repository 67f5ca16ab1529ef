"""The objectives' declarations for lossy teacher stores (:meth:`distilkit.cards.base.TermCard.teacher_voxels` and
``teacher_softmax``), checked against the computations: a term that declares ``valid``/``occupied`` for a teacher role
gives the same value and gradients whatever the teacher holds outside that mask (and another value when the inside
changes); a term that declares a role softmax-only gives the same value and gradients when a per-voxel constant is
added to that role's class scores (and another value when they are scaled). Small float64 inputs on a 4 x 4 x 3 grid,
labels with ignored (255) and empty (0) voxels."""

from __future__ import annotations

from typing import Any

import pytest
import torch

from distilkit.cards.base import TermCard
from distilkit.data.batch import Batch
from distilkit.registry import OBJECTIVES
from distilkit.structures import SparseVoxels

B, K, C, SHAPE = 2, 4, 3, (4, 4, 3)
IGNORE = 255
MASKS = ("all", "valid", "occupied")

# parameters each objective is checked with (default: its defaults only); small samples for hassc_hvm
PARAMS: dict[str, list[dict[str, Any]]] = {
    "kd": [{"voxels": v, "temperature": 2.0} for v in MASKS],
    "dist": [{"voxels": v, "temperature": 2.0} for v in MASKS],
    "pvkd": [{"voxels": v, "temperature": 2.0} for v in MASKS],
    "l2cocc_pad": [{"include_empty": False}, {"include_empty": True}],
    "l2cocc_fsd": [{"reduce": "per_sample"}, {"reduce": "pooled"}],
    "hassc_kd": [{"temperature": 2.0}, {"temperature": 1.0, "dynamic_weight": False},
                 {"per": "batch", "classes": "all"}],
    "hassc_hvm": [{"points": 8, "oversample": 3, "omega": 0.5, "delta": 1.0, "rank": "probabilities"},
                  {"points": 8, "oversample": 3, "omega": 0.5, "delta": 1.0, "rank": "logits"},
                  {"points": 8, "oversample": 3, "omega": 0.5, "delta": 0.0}],
    "rgo2d": [{}, {"local": 0.0}],
    "cleaners": [{}, {"kd_sa": 0.0}],
}

# objectives with a `voxels` parameter that nevertheless read every voxel of the teacher (none so far), and why
READS_ALL: dict[str, str] = {}


def _overrides(card: type, method: str) -> bool:
    return getattr(card, method).__func__ is not getattr(TermCard, method).__func__


def declaring() -> list[str]:
    return [e.name for e in OBJECTIVES
            if _overrides(e.card, "teacher_voxels") or _overrides(e.card, "teacher_softmax")]


def cases(check: str) -> list[Any]:
    """(objective, parameter set) pairs whose declaration has something to check: ``voxels``, a teacher role read
    at fewer than all voxels; ``softmax``, a role read through its softmax only."""
    out = []
    for name in declaring():
        card = OBJECTIVES.card(name)
        for i, given in enumerate(PARAMS.get(name, [{}])):
            params = card.Params(**given)
            if (check == "voxels" and set(card.teacher_voxels(params).values()) != {"all"}) or \
                    (check == "softmax" and card.teacher_softmax(params)):
                out.append(pytest.param(name, i, id=f"{name}-{i}"))
    return out


def labels(seed: int) -> torch.Tensor:
    """(B, X, Y, Z) labels 0..K-1 with about a quarter ignored and a third empty; every sample has each kind."""
    g = torch.Generator().manual_seed(seed)
    lab = torch.randint(1, K, (B, *SHAPE), generator=g)
    u = torch.rand(B, *SHAPE, generator=g)
    lab[u < 0.55] = 0
    lab[u < 0.25] = IGNORE
    lab[:, 0, 0, 0], lab[:, 0, 0, 1], lab[:, 0, 0, 2] = IGNORE, 0, 1
    return lab


def value_of(kind: str, g: torch.Generator) -> Any:
    if kind == "voxel_logits":
        return torch.randn(B, K, *SHAPE, generator=g, dtype=torch.float64) * 2
    if kind in ("feature_map", "volume_features"):
        return torch.randn(B, C, *SHAPE, generator=g, dtype=torch.float64)
    if kind == "bev_features":  # the grid's bird's-eye plane
        return torch.randn(B, C, *SHAPE[:2], generator=g, dtype=torch.float64)
    if kind == "sparse_features":
        grid = torch.stack(torch.meshgrid(*[torch.arange(n) for n in SHAPE], indexing="ij"), -1).reshape(-1, 3)
        coords = torch.cat([torch.cat([torch.full((len(grid), 1), b), grid], 1) for b in range(B)])
        return SparseVoxels(coords, torch.randn(len(coords), C, generator=g, dtype=torch.float64), SHAPE)
    raise AssertionError(f"no test input for a {kind} tap")


def build(name: str, i: int, seed: int = 0) -> tuple[Any, dict[str, Any], Batch]:
    """The term ``name`` with its ``i``-th parameters, set up, and role values: every tap role of its card (the
    optional ones too), ``target`` the labels, any other batch role (rgo2d's scribbles) the labels with some voxels
    unlabelled (254)."""
    entry = OBJECTIVES.entry(name)
    cls = entry.obj
    obj = cls(cls.Params(**PARAMS.get(name, [{}])[i]))
    g = torch.Generator().manual_seed(seed)
    taps: dict[str, Any] = {role: value_of(kind, g) for role, kind in cls.CONSUMES.items()}
    target = labels(seed)
    for role in cls.BATCH:
        if role == "target":
            taps[role] = target
        else:
            other = target.clone()
            other[torch.rand(B, *SHAPE, generator=g) < 0.3] = 254
            taps[role] = other
    batch = Batch({}, {"voxel_target": target}, {"size": B})
    obj.setup(taps, batch)
    if name == "hassc_hvm":  # its class weights come from the training split (prepare)
        obj.class_weight = torch.linspace(0.5, 1.5, K)
    obj.double()
    return obj, taps, batch


def run(obj: Any, taps: dict[str, Any], batch: Batch) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The term's value and its gradients into every student tap and its own parameters (the same random draws
    on every call)."""
    students = []
    fed: dict[str, Any] = {}
    for role, value in taps.items():
        if role in obj.CONSUMES and role not in obj.TEACHER_ROLES:
            if isinstance(value, SparseVoxels):
                value = SparseVoxels(value.coords, value.feats.clone().requires_grad_(True), value.spatial_shape)
                students.append(value.feats)
            else:
                value = value.clone().requires_grad_(True)
                students.append(value)
        fed[role] = value
    torch.manual_seed(7)
    out = obj.compute(fed, batch)
    wrt = students + [p for p in obj.parameters() if p.requires_grad]
    grads = torch.autograd.grad(out, wrt, allow_unused=True)
    return out.detach(), [torch.zeros_like(w) if gr is None else gr for w, gr in zip(wrt, grads)]


def assert_same(a: tuple[torch.Tensor, list[torch.Tensor]], b: tuple[torch.Tensor, list[torch.Tensor]],
                what: str) -> None:
    torch.testing.assert_close(b[0], a[0], rtol=1e-12, atol=1e-12, msg=lambda m: f"{what}: the value moved: {m}")
    for ga, gb in zip(a[1], b[1]):
        torch.testing.assert_close(gb, ga, rtol=1e-10, atol=1e-12, msg=lambda m: f"{what}: a gradient moved: {m}")


def mask_of(target: torch.Tensor, which: str) -> torch.Tensor:
    valid = target != IGNORE
    return valid if which == "valid" else valid & (target != 0)


def with_teacher(taps: dict[str, Any], role: str, value: torch.Tensor) -> dict[str, Any]:
    return {**taps, role: value}


def teacher_is_read(name: str, obj: Any) -> bool:
    """Whether the term reads its teacher at all with these parameters (hassc_hvm with delta 0 does not)."""
    return not (name == "hassc_hvm" and obj.params.delta == 0)


@pytest.mark.parametrize("name,i", cases("voxels"))
def test_teacher_values_outside_the_declared_voxels_change_nothing(name, i) -> None:
    obj, taps, batch = build(name, i)
    declared = obj.teacher_voxels(obj.params)
    assert set(declared) == set(obj.TEACHER_ROLES) and set(declared.values()) <= set(MASKS), declared
    base = run(obj, taps, batch)
    assert torch.isfinite(base[0]) and float(base[0]) != 0.0
    g = torch.Generator().manual_seed(11)
    checked = 0
    for role, which in declared.items():
        if which == "all":
            continue
        teacher = taps[role]
        assert isinstance(teacher, torch.Tensor) and tuple(teacher.shape[2:]) == SHAPE, (role, "not on the grid")
        outside = (~mask_of(taps["target"], which))[:, None].to(teacher.dtype)
        assert 0 < float(outside.mean()) < 1
        noise = torch.randn(teacher.shape, generator=g, dtype=teacher.dtype) * 50
        assert_same(base, run(obj, with_teacher(taps, role, teacher + noise * outside), batch), f"{role} noised")
        # what a store with this mask reads back: zeros outside
        assert_same(base, run(obj, with_teacher(taps, role, teacher * (1 - outside)), batch), f"{role} zeroed")
        if teacher_is_read(name, obj):  # the inside counts: the test can fail
            moved = run(obj, with_teacher(taps, role, teacher + noise * (1 - outside)), batch)
            assert abs(float(moved[0] - base[0])) > 1e-6, f"{role}: the inside of the mask changes nothing"
        checked += 1
    assert checked


@pytest.mark.parametrize("name,i", cases("softmax"))
def test_softmax_roles_ignore_a_per_voxel_shift(name, i) -> None:
    obj, taps, batch = build(name, i)
    roles = obj.teacher_softmax(obj.params)
    assert roles and roles <= obj.TEACHER_ROLES
    base = run(obj, taps, batch)
    g = torch.Generator().manual_seed(13)
    for role in roles:
        assert obj.CONSUMES[role] == "voxel_logits", role
        teacher = taps[role]
        shift = torch.randn(B, 1, *SHAPE, generator=g, dtype=teacher.dtype) * 3  # one constant per voxel
        assert_same(base, run(obj, with_teacher(taps, role, teacher + shift), batch), f"{role} shifted")
        if not teacher_is_read(name, obj):
            continue
        # the scores scaled (a sharper softmax) move the value, so the test can fail; hassc_hvm's teacher only
        # picks positions by the ranking of its hardness, which scaling may keep: its scores noised class by class
        ranks = name == "hassc_hvm"
        other = teacher + torch.randn(teacher.shape, generator=g, dtype=teacher.dtype) * 3 if ranks else teacher * 2
        moved = run(obj, with_teacher(taps, role, other), batch)
        assert abs(float(moved[0] - base[0])) > 1e-6, f"{role}: other class scores change nothing"


def test_every_voxels_parameter_is_declared() -> None:
    """An objective with a ``voxels`` parameter declares which teacher voxels it reads (or is listed here with the
    reason it reads all), and the declaration follows the parameter."""
    with_param = [e for e in OBJECTIVES if "voxels" in getattr(e.card, "Params").model_fields]
    assert {"kd", "dist", "pvkd"} <= {e.name for e in with_param}
    for e in with_param:
        if e.name in READS_ALL:
            continue
        assert _overrides(e.card, "teacher_voxels"), f"{e.name}: a voxels parameter but no teacher_voxels"
        for which in MASKS:
            declared = e.card.teacher_voxels(e.card.Params(voxels=which))
            assert which in declared.values(), (e.name, which, declared)


def test_declarations_are_well_formed_for_every_objective() -> None:
    """Every objective's declarations, at its default parameters: the roles are its teacher roles, the masks known,
    the softmax-only roles class scores (voxel_logits); cards stay torch-free (checked by lint-imports)."""
    for e in OBJECTIVES:
        card = e.card
        params = card.Params()
        voxels = card.teacher_voxels(params)
        assert set(voxels) == set(card.TEACHER_ROLES) and set(voxels.values()) <= set(MASKS), (e.name, voxels)
        for role, which in voxels.items():
            if which != "all":
                assert "target" in card.BATCH, (e.name, role, "a mask needs the target labels")
        soft = card.teacher_softmax(params)
        assert soft <= card.TEACHER_ROLES and all(card.CONSUMES[r] == "voxel_logits" for r in soft), (e.name, soft)
    assert len(declaring()) >= 9
