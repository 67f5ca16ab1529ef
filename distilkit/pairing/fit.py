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
from distilkit.pairing.rules import PLANE, TapPair
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


def _params(card: Any) -> Any:
    """The card's default parameters (None where it has no ``Params`` a plain call builds: a plug-in's)."""
    try:
        return card.Params()
    except Exception:
        return None


def _pair_for(card: Any, params: Any, t_role: str, pairs: list[TapPair], info: Any, teacher: ModelFacts,
              forced: dict[str, str] | None = None) -> tuple[TapPair | None, str | None, str]:
    """The best pair for teacher role ``t_role`` and its student partner under the card's ``params``: (pair,
    connector, problem); ``forced`` (role -> tap, ``--taps``): only pairs on those taps. A role without a declared
    match (a plug-in's) takes the best pair of its kinds: its first step decides."""
    s_role, m = partner(t_role), card.match(params).get(t_role)
    wanted_s, wanted_t = card.CONSUMES[s_role], card.CONSUMES[t_role]
    forced = {r: t for r, t in (forced or {}).items() if r in (s_role, t_role)}

    def made_ok(p: TapPair) -> bool:  # init's own bird's-eye maps serve the roles that read bird's-eye maps only
        return ((p.student.of is None or wanted_s == PLANE or forced.get(s_role) == p.student.tap)  # or --taps
                and (p.teacher.of is None or wanted_t == PLANE or forced.get(t_role) == p.teacher.tap))

    def as_forced(p: TapPair) -> bool:
        return forced.get(s_role, p.student.tap) == p.student.tap and forced.get(t_role, p.teacher.tap) == p.teacher.tap

    candidates = [p for p in pairs if kind_fits(p.student.kind, wanted_s) and kind_fits(p.teacher.kind, wanted_t)
                  and made_ok(p)]
    if forced:
        kept = [p for p in candidates if as_forced(p)]
        if not kept:
            return None, None, _forced_problem(forced, s_role, t_role, wanted_s, wanted_t, pairs)
        candidates = kept
    if not candidates:
        if not teacher.of_kind(wanted_t):
            return None, None, f"the teacher {teacher.adapter!r} has no {wanted_t} tap"
        return None, None, (f"no student {wanted_s} tap aligns with a teacher {wanted_t} tap (other kinds, grids "
                            "or planes)")
    if m is None:
        return candidates[0], None, ""
    first = ""
    for p in candidates:
        problem = _match_problem(m, p, info)
        connector, width = _connector(m, s_role, p)
        if problem is None and width is None:
            return p, connector, ""
        first = first or (problem or width or "")
    return None, None, first


def _forced_problem(forced: dict[str, str], s_role: str, t_role: str, wanted_s: str, wanted_t: str,
                   pairs: list[TapPair]) -> str:
    """Why the taps ``--taps`` names make no pair the roles read: a name that is no tap of its model (its taps
    listed), a tap of another kind, or two taps that do not align."""
    taps = {"student": {p.student.tap: p.student for p in pairs}, "teacher": {p.teacher.tap: p.teacher for p in pairs}}
    for role, model, kind in ((s_role, "student", wanted_s), (t_role, "teacher", wanted_t)):
        tap = forced.get(role)
        if tap is None:
            continue
        if tap not in taps[model]:
            return (f"--taps: {role}={tap}: no tap of the {model} that aligns with any of the other's (the "
                    f"{model}'s in pairs: {', '.join(sorted(taps[model])) or 'none'}; `--show` lists them)")
        fact = taps[model][tap]
        if not kind_fits(fact.kind, kind):
            return f"--taps: {role}={tap}: a {fact.kind} tap, and {role} reads a {kind} tap"
        if fact.of is not None and kind != PLANE and forced.get(partner(role)) is None:
            return (f"--taps: {role}={tap} is a bird's-eye map init makes: name the {partner(role)} side's tap too "
                    "(init offers its maps to other terms only when both are named)")
    named = ", ".join(f"{r}={t}" for r, t in forced.items())
    return (f"--taps: {named}: no pair it reads (a student {wanted_s} tap aligned with a teacher {wanted_t} tap; "
            "`--show` lists the pairs)")


def _own_tap(card: Any, role: str, kind: str, student: ModelFacts, forced: str | None = None
             ) -> tuple[str | None, str]:
    """The student tap of a role only the student fills (a head's features, a sampler's points): ``forced``
    (``--taps``) where it is a returned tap of that kind, else the first tap the card's ``TAP_HINTS`` prefers, else
    (none of them declared) the first of its kind, said in the note; (None, why) where there is none, or a
    preferred tap is declared but not returned with these parameters."""
    hinted = card.TAP_HINTS.get(role, ())
    declared = [t for t in student.taps if kind_fits(t.kind, kind) and t.of is None]
    present = [t.tap for t in declared if t.present]
    if forced is not None:
        return (forced, "") if forced in present else (None, f"--taps: {role} reads a student {kind} tap, and "
                                                            f"{forced!r} is not one {student.adapter!r} returns")
    preferred = [t for t in hinted if t in present]
    if preferred:
        return preferred[0], ""
    absent = [t.tap for t in declared if not t.present and t.tap in hinted]
    if absent:
        return None, (f"{role} reads {', '.join(absent)}, which {student.adapter!r} declares but does not return "
                      "with these parameters (e.g. a sampler's samples only in its few-step generator's training)")
    if present:
        return present[0], (f"{role}: {present[0]} (the objective prefers {', '.join(hinted)})" if hinted else "")
    return None, f"{role} reads a student {kind} tap, and {student.adapter!r} has none"


def propose(name: str, card: Any, weight: float, pairs: list[TapPair], student: ModelFacts, teacher: ModelFacts,
            info: Any, forced: dict[str, str] | None = None) -> Proposal:
    """Objective ``name`` on its best taps of the pair (``forced``, role -> tap: on those), or the reason it does
    not fit."""
    out = Proposal(name, weight, teacher_roles=frozenset(card.TEACHER_ROLES))
    missing = [f"{role}: " + (card.BATCH_HINTS.get(role) or
                              f"needs the batch field {card.default_field(role, info.fields)!r}")
               for role in card.BATCH if card.default_field(role, info.fields) not in info.fields]
    params = _params(card)
    lacks_t = sorted(card.REQUIRES - teacher.capabilities)
    lacks_s = sorted((card.student_requires(params) if params is not None else card.STUDENT_REQUIRES)
                     - student.capabilities)
    if missing:
        out.refused = "the data lacks " + "; ".join(missing)
    elif lacks_t:
        out.refused = f"calls the teacher's {', '.join(f'{m}()' for m in lacks_t)}, which {teacher.adapter!r} lacks"
    elif lacks_s:
        out.refused = f"calls the student's {', '.join(f'{m}()' for m in lacks_s)}, which {student.adapter!r} lacks"
    if out.refused:
        return out
    notes = []
    if card.TEACHER_ROLES and not card.match(params):
        notes.append("its card declares no match: checked by its first step")
    named = set(forced or {})  # --taps: an optional role named (or its partner) is read too
    wanted = {r for r in card.TEACHER_ROLES if r not in card.OPTIONAL or {r, partner(r)} & named}
    for t_role in sorted(wanted, key=lambda r: r != "teacher"):
        pair, connector, problem = _pair_for(card, params, t_role, pairs, info, teacher, forced)
        if pair is None:
            out.refused, out.taps = problem, {}
            return out
        out.taps.update({partner(t_role): pair.student.tap, t_role: pair.teacher.tap})
        out.pairs[t_role] = pair
        if partner(t_role) == "student":
            out.connector = connector
            if connector and pair.student.channels is None and not student.probed:  # --static: no widths
                notes.append(f"connector {connector}: widths unknown without a forward (--static)")
    for role, kind in card.CONSUMES.items():
        if role in out.taps or (role in card.OPTIONAL and role not in named) or role in card.TEACHER_ROLES:
            continue
        tap, note = _own_tap(card, role, kind, student, (forced or {}).get(role))
        if tap is None:
            out.refused, out.taps = note, {}
            return out
        out.taps[role] = tap
        notes += [note] if note else []
    if not card.TEACHER_ROLES and not card.REQUIRES:
        notes.append("needs no teacher (it compares the student with the data)")
    out.note = "; ".join(notes)
    return out


def proposals(pairs: list[TapPair], student: ModelFacts, teacher: ModelFacts, info: Any,
              forced: dict[str, dict[str, str]] | None = None) -> list[Proposal]:
    """Every registered objective's proposal for this pair, in the registry's order (``forced``: objective ->
    role -> tap, from ``--taps``)."""
    from distilkit.registry import OBJECTIVES

    forced = forced or {}
    return [propose(n, OBJECTIVES.card(n), float(OBJECTIVES.entry(n).meta["default_weight"]), pairs, student,
                    teacher, info, forced.get(n)) for n in OBJECTIVES.names()]


def check_forced(forced: dict[str, dict[str, str]]) -> list[str]:
    """The problems of ``--taps`` (objective -> role -> tap): a role the objective does not read."""
    from distilkit.registry import OBJECTIVES

    out = []
    for name, roles in forced.items():
        card = OBJECTIVES.card(name)
        for r in roles:
            if r in card.BATCH:
                out.append(f"--taps {name}.{r}: {r} is a field of the batch, not a model's tap: name the field in "
                           f"the written recipe's term (taps: {{{r}: FIELD}})")
            elif r not in card.CONSUMES:
                out.append(f"--taps {name}.{r}: {name} reads no role {r!r} (its roles: {', '.join(card.CONSUMES)})")
    return out


def defaults(found: list[Proposal]) -> list[Proposal]:
    """What ``--yes`` chooses from ``found``: the first that fits of each group of :data:`DEFAULTS`."""
    by_name = {p.objective: p for p in found if p.fits}
    return [by_name[g] for group in DEFAULTS for g in [next((n for n in group if n in by_name), None)] if g]


__all__ = ["DEFAULTS", "Proposal", "check_forced", "defaults", "proposals", "propose"]
