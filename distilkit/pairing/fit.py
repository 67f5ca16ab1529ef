"""Which registered objectives fit a pair of models, and on which taps (torch-free): each objective's card says
what it reads (``CONSUMES``), how each teacher tap must match its student partner's (``match()``: channels and
spatial rules, tested against the objective), the batch fields and the models' methods it needs; a proposal is an
objective with its taps and connector, or the reason it does not fit."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from distilkit.cards.base import partner
from distilkit.geometry.grids import grid_factors
from distilkit.pairing.facts import ModelFacts
from distilkit.pairing.rules import TapPair
from distilkit.taps import kind_fits

# what `--yes` chooses, in order: the first of each group that fits (a group of one: that objective if it fits)
DEFAULTS: tuple[tuple[str, ...], ...] = (("kd",), ("dskd", "fitnets", "monoocc_image"), ("vsd",))


@dataclass
class Proposal:
    """An objective on taps of the pair (role -> tap), its connector on the student role, default weight and a
    note on the choice; ``refused``: why it does not fit (then ``taps`` is empty)."""

    objective: str
    weight: float
    taps: dict[str, str] = field(default_factory=dict)
    connector: str | None = None
    pairs: dict[str, TapPair] = field(default_factory=dict)  # teacher role -> its pair
    teacher_roles: frozenset[str] = frozenset()  # the roles whose taps are the teacher's
    note: str = ""
    refused: str = ""

    @property
    def fits(self) -> bool:
        return not self.refused


def _match_problem(m: Any, pair: TapPair, info: Any) -> str | None:
    """Why ``pair`` breaks the teacher role's rule ``m`` (None: it keeps it)."""
    if (m.spatial == "collapsed") != (pair.how == "collapsed"):
        return ("reads a bird's-eye map against the voxels it collapses" if m.spatial == "collapsed" else
                f"reads {pair.teacher.kind} on the student's kind of tap, not voxels collapsed")
    if m.spatial == "same" and not pair.same:
        return f"compares {pair.kind} cell by cell, and {pair.student.tap} and {pair.teacher.tap} are {pair.how}"
    if m.spatial == "aligned" and pair.kind != "sparse_features":
        return "matches sparse voxels across grids: it reads sparse features"
    if m.on_labels:
        grid = pair.student.grid
        how = grid_factors(info.grid, grid) if grid is not None and info.grid is not None else "no voxel grid"
        if isinstance(how, str) or how[0] == "finer":
            return (f"masks the maps by the labels pooled to their size: {pair.student.tap} is not on the labels' "
                    "grid or a coarsening of it")
    return None


def _connector(m: Any, role: str, pair: TapPair) -> tuple[str | None, str | None]:
    """(the connector the student role needs, or a problem) for the channel rule ``m``."""
    cs, ct = pair.student.channels, pair.teacher.channels
    if m.channels != "equal" or pair.how == "collapsed" or (cs is not None and cs == ct):
        return None, None
    if role != "student":
        return None, f"needs equal widths on {role}, where no connector projects ({cs} and {ct} channels)"
    return "linear", None


def _pair_for(card: Any, t_role: str, pairs: list[TapPair], info: Any) -> tuple[TapPair | None, str | None, str]:
    """The best pair for teacher role ``t_role`` and its student partner: (pair, connector, problem)."""
    s_role, m = partner(t_role), card.match()[t_role]
    wanted_s, wanted_t = card.CONSUMES[s_role], card.CONSUMES[t_role]
    candidates = [p for p in pairs if kind_fits(p.student.kind, wanted_s) and kind_fits(p.teacher.kind, wanted_t)]
    if not candidates:
        return None, None, f"no student {wanted_s} tap aligns with a teacher {wanted_t} tap"
    first = ""
    for p in candidates:
        problem = _match_problem(m, p, info)
        connector, width = _connector(m, s_role, p)
        if problem is None and width is None:
            return p, connector, ""
        first = first or (problem or width or "")
    return None, None, first


def propose(name: str, card: Any, weight: float, pairs: list[TapPair], student: ModelFacts, teacher: ModelFacts,
            info: Any) -> Proposal:
    """Objective ``name`` on its best taps of the pair, or the reason it does not fit."""
    out = Proposal(name, weight, teacher_roles=frozenset(card.TEACHER_ROLES))
    missing = [f"{role}: {card.BATCH_HINTS.get(role) or f'needs the batch field {card.default_field(role, info.fields)!r}'}"
               for role in card.BATCH if card.default_field(role, info.fields) not in info.fields]
    lacks_t = sorted(card.REQUIRES - teacher.capabilities)
    lacks_s = sorted(card.student_requires(card.Params()) - student.capabilities)
    if missing:
        out.refused = "the data lacks " + "; ".join(missing)
    elif lacks_t:
        out.refused = f"calls the teacher's {', '.join(f'{m}()' for m in lacks_t)}, which {teacher.adapter!r} lacks"
    elif lacks_s:
        out.refused = f"calls the student's {', '.join(f'{m}()' for m in lacks_s)}, which {student.adapter!r} lacks"
    if out.refused:
        return out
    for t_role in sorted(card.TEACHER_ROLES - card.OPTIONAL, key=lambda r: r != "teacher"):
        pair, connector, problem = _pair_for(card, t_role, pairs, info)
        if pair is None:
            out.refused, out.taps = problem, {}
            return out
        out.taps.update({partner(t_role): pair.student.tap, t_role: pair.teacher.tap})
        out.pairs[t_role] = pair
        if partner(t_role) == "student":
            out.connector = connector
    for role, kind in card.CONSUMES.items():  # the student's own roles (a head's features, a sampler's points)
        if role in out.taps or role in card.OPTIONAL or role in card.TEACHER_ROLES:
            continue
        hinted = card.TAP_HINTS.get(role)  # where the card names the taps a role reads, only those
        taps = [f.tap for f in student.of_kind(kind) if hinted is None or f.tap in hinted]
        if not taps:
            absent = [t.tap for t in student.taps if not t.present and kind_fits(t.kind, kind)
                      and (hinted is None or t.tap in hinted)]
            why = (f"does not return {', '.join(absent)} with these parameters" if absent else
                   f"has none{' of ' + ', '.join(hinted) if hinted else ''}")
            out.refused, out.taps = f"{role} reads a student {kind} tap, and {student.adapter!r} {why}", {}
            return out
        out.taps[role] = taps[0]
    if not card.TEACHER_ROLES and not card.REQUIRES:
        out.note = "needs no teacher (it compares the student with the data)"
    return out


def proposals(pairs: list[TapPair], student: ModelFacts, teacher: ModelFacts, info: Any) -> list[Proposal]:
    """Every registered objective's proposal for this pair, in the registry's order."""
    from distilkit.registry import OBJECTIVES

    return [propose(n, OBJECTIVES.card(n), float(OBJECTIVES.entry(n).meta["default_weight"]), pairs, student,
                    teacher, info) for n in OBJECTIVES.names()]


def defaults(found: list[Proposal]) -> list[Proposal]:
    """What ``--yes`` chooses from ``found``: the first that fits of each group of :data:`DEFAULTS`."""
    by_name = {p.objective: p for p in found if p.fits}
    return [by_name[g] for group in DEFAULTS for g in [next((n for n in group if n in by_name), None)] if g]


__all__ = ["DEFAULTS", "Proposal", "defaults", "proposals", "propose"]
