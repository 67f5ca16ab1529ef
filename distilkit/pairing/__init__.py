"""``distilkit init``'s logic: a teacher and a student (adapter names and parameters) and a dataset become a plan —
the taps both models expose (from their cards, then one forward on a dry batch), the pairs of taps that align, the
objectives that fit each pair (from the objectives' cards), the chosen ones — and the plan a commented recipe that
``validate`` accepts (:mod:`~distilkit.pairing.write`, :mod:`~distilkit.pairing.confirm`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from distilkit.pairing.facts import ModelFacts, TapFact, card_facts, with_bev, with_probe
from distilkit.pairing.fit import DEFAULTS, Proposal, check_forced, defaults, proposals
from distilkit.pairing.inputs import (InitError, aux_stages, check_models, data_params_for, dataset_reasons,
                                      from_checkpoint, lookup, pick_dataset, serves)
from distilkit.pairing.rules import TapPair, tap_pairs


@dataclass
class Plan:
    """Everything a written recipe comes from: the models (role -> (adapter, params)), the data, the auxiliary
    stages (stage -> (adapter, params)) and each role's aux edges (input -> stage), the facts, pairs, every
    objective's proposal and the chosen ones."""

    name: str
    dataset: str
    data_params: dict[str, Any]
    models: dict[str, tuple[str, dict[str, Any]]]
    aux_stages: dict[str, tuple[str, dict[str, Any]]] = field(default_factory=dict)
    aux: dict[str, dict[str, str]] = field(default_factory=dict)
    facts: dict[str, ModelFacts] = field(default_factory=dict)
    pairs: list[TapPair] = field(default_factory=list)
    found: list[Proposal] = field(default_factory=list)
    chosen: list[Proposal] = field(default_factory=list)
    grid_text: str = ""
    baseline: bool = True
    each: bool = False
    teacher_checkpoint: str | None = None  # a trained teacher: no teacher stage, its checkpoint read by the students
    task_note: str = ""  # why the student's default task losses are left out (they read taps it does not return)


def _task_note(student: ModelFacts) -> str:
    """Why the student's default task losses cannot train it with these parameters (they name taps the probed
    forward did not return: a ScoreLiDAR student, ``generate_steps > 0``, returns samples, not a denoiser's
    noise), or ""."""
    absent = {t.tap for t in student.taps if not t.present}
    broken = {loss["name"]: sorted(set(loss.get("taps", {}).values()) & absent)
              for loss in student.card.DEFAULT_TASK_LOSSES}
    broken = {name: taps for name, taps in broken.items() if taps}
    if not broken:
        return ""
    return ("no task loss: " + "; ".join(f"{name} (the student's default) reads {', '.join(taps)}"
                                         for name, taps in broken.items())
            + ", which its forward does not return with these parameters")


def plan(teacher: str, student: str, *, teacher_params: dict[str, Any] | None = None,
         student_params: dict[str, Any] | None = None, dataset: str | None = None,
         data_params: dict[str, Any] | None = None, objectives: list[str] | None = None, static: bool = False,
         name: str | None = None, require: bool = True, taps: dict[str, dict[str, str]] | None = None) -> Plan:
    """The plan for a ``teacher`` and a ``student`` adapter: facts (probed unless ``static``), pairs, proposals,
    and the chosen objectives (``objectives``, each on its best pair, or the defaults of
    :data:`~distilkit.pairing.fit.DEFAULTS` that fit; ``require``: an error when none fits, else an empty
    choice, for ``--show`` and the questions). ``taps`` (objective -> role -> tap, ``--taps``): those objectives on
    those taps, chosen beside ``objectives`` (or alone). Raises :class:`InitError` naming what is wrong."""
    from distilkit.errors import RecipeError
    from distilkit.pairing.confirm import resolved
    from distilkit.registry import ADAPTERS, DATASETS, OBJECTIVES, load_plugins

    load_plugins()
    for adapter in (teacher, student):
        lookup(ADAPTERS, adapter)
    models = {"teacher": (teacher, dict(teacher_params or {})), "student": (student, dict(student_params or {}))}
    check_models(models)
    given = dict(data_params or {})
    if dataset is None:
        dataset = pick_dataset(models, given)
    lookup(DATASETS, dataset)
    taps = dict(taps or {})
    for o in [*(objectives or []), *taps]:
        lookup(OBJECTIVES, o)
    problems = check_forced(taps)
    if problems:
        raise InitError("; ".join(problems))
    if taps:
        objectives = [*(objectives or []), *(o for o in taps if o not in (objectives or []))]
    params = data_params_for(dataset, given, [ADAPTERS.card(a) for a, _ in models.values()])
    why, info = serves(dataset, params, models)
    if why is not None:
        raise InitError(why)
    out = Plan(name or f"{student}_from_{teacher}".replace("-", "_"), dataset, params, models)
    probe_recipe = {"schema_version": 1, "name": out.name, "seed": 0,
                    "data": {"dataset": dataset, "params": params}, "stages": {}}
    out.aux_stages, out.aux = aux_stages(models, info)
    stages = {n: {"model": {"adapter": a, "params": p}} for n, (a, p) in out.aux_stages.items()}
    for role, (adapter, p) in models.items():
        stages[role] = {"model": {"adapter": adapter, "params": p},
                        **({"aux": {f: {"from": s} for f, s in out.aux[role].items()}} if out.aux.get(role) else {})}
    try:
        res = resolved({**probe_recipe, "stages": stages})
    except RecipeError as exc:
        raise InitError("; ".join(f"{f}: {p}" if f else p for f, p in exc.problems)) from None
    info = res.data_info
    out.grid_text = "x".join(map(str, info.grid.shape)) + f" ({info.grid.voxel_size:g} m)" if info.grid else ""
    for role in ("teacher", "student"):
        out.facts[role] = card_facts(role, res.stages[role].student, info, models[role][1])
    if not static:
        from distilkit.pairing.probe import probe_taps

        try:
            probed = probe_taps(res, {"teacher": "teacher", "student": "student"})
        except Exception as exc:  # a model whose forward fails on the dry batch: said, not a traceback
            from distilkit.engine.train.oom import is_out_of_memory

            if is_out_of_memory(exc):
                raise
            raise InitError(f"running the models once on a dry batch failed ({type(exc).__name__}: {exc}); "
                            "--static reads their taps from the cards alone") from None
        out.facts = {role: with_probe(f, probed[role]) for role, f in out.facts.items()}
    out.facts = {role: with_bev(f) for role, f in out.facts.items()}
    out.task_note = _task_note(out.facts["student"])
    if out.task_note:
        out.baseline = False
    out.pairs = tap_pairs(out.facts["student"], out.facts["teacher"])
    out.found = proposals(out.pairs, out.facts["student"], out.facts["teacher"], info, taps)
    by_name = {p.objective: p for p in out.found}
    if objectives:
        refused = [f"{o}: {by_name[o].refused}" for o in objectives if not by_name[o].fits]
        if refused:
            raise InitError(f"{student} <- {teacher} on {dataset}: " + "; ".join(refused))
        out.chosen = [by_name[o] for o in objectives]
    else:
        out.chosen = defaults(out.found)
        if not out.chosen and require:
            wanted = [n for group in DEFAULTS for n in group]
            raise InitError(f"{student} <- {teacher} on {dataset}: no objective fits — "
                            + "; ".join(f"{n}: {by_name[n].refused}" for n in wanted if n in by_name))
    return out


__all__ = ["InitError", "ModelFacts", "Plan", "Proposal", "TapFact", "TapPair", "dataset_reasons", "pick_dataset",
           "plan"]
