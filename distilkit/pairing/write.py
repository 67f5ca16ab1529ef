"""The recipe ``distilkit init`` writes, as a dict and as commented YAML text: the teacher's stage (trained here),
the auxiliary stages a model's inputs need, the student without distillation (the baseline every table compares
with) and the student with the chosen objectives, every tap named so that the file documents the choice, and a
comment on each term saying which taps it pairs and why."""

from __future__ import annotations

import json
import shlex
from typing import Any

import yaml

from distilkit.pairing.fit import Proposal

# objectives that distil into a generator initialised as its teacher (ScoreLiDAR, Distillation-DPO)
INIT_FROM_TEACHER = frozenset({"vsd", "distillation_dpo"})
WEIGHTS_NOTE = ("weights are each objective's default, its paper's for its own setting, not tuned for this pair: "
                "compare a few in a sweep (distilkit sweep, e.g. recipes/sweeps/dskd_weight.yaml)")


def _model(adapter: str, params: dict[str, Any]) -> dict[str, Any]:
    return {"adapter": adapter, **({"params": dict(params)} if params else {})}


def _term(p: Proposal) -> dict[str, Any]:
    out: dict[str, Any] = {"name": p.objective, "weight": p.weight, "taps": dict(p.taps)}
    if p.connector:
        out["connector"] = p.connector
    return out


def recipe_dict(plan: Any) -> dict[str, Any]:
    """The recipe of ``plan`` (a :class:`distilkit.pairing.Plan`)."""
    stages: dict[str, Any] = {}
    for name, (adapter, params) in plan.aux_stages.items():
        stages[name] = {"label": f"{adapter} (its prediction is the input {name!r})", "model": _model(adapter, params)}

    def stage(role: str, label: str, teacher: bool = False) -> dict[str, Any]:
        """A stage of ``role``'s model; with its ``teacher``, the aux edges both models read (one batch)."""
        out: dict[str, Any] = {"label": label, "model": _model(*plan.models[role])}
        edges = {**plan.aux.get(role, {}), **(plan.aux.get("teacher", {}) if teacher else {})}
        if edges:
            out["aux"] = {field: {"from": name} for field, name in edges.items()}
        return out

    t_adapter, s_adapter = plan.models["teacher"][0], plan.models["student"][0]
    if plan.teacher_checkpoint is None:
        stages["teacher"] = stage("teacher", f"{t_adapter} teacher")
        edge: dict[str, Any] = {"from": "teacher"}
    else:  # a trained teacher: read from its checkpoint by each student that distils
        edge = {"checkpoint": plan.teacher_checkpoint, "model": _model(*plan.models["teacher"])}
    if plan.baseline:
        stages["student"] = stage("student", f"{s_adapter} student, no distillation (the baseline)")
    groups = [[p] for p in plan.chosen] if plan.each else [plan.chosen]
    for group in groups:
        names = "_".join(p.objective for p in group)
        s = stage("student", f"{s_adapter} student <- {t_adapter} ({', '.join(p.objective for p in group)})", True)
        s["teacher"] = dict(edge)
        if plan.teacher_checkpoint is None and t_adapter == s_adapter and \
                {p.objective for p in group} & INIT_FROM_TEACHER:
            s["init"] = {"from": "teacher", "strict": False}  # a few-step generator starts as the teacher
        made = _made_taps(plan, group)
        if made["student"]:
            s["model"]["taps"] = made["student"]
        if made["teacher"]:
            s["teacher"]["taps"] = made["teacher"]
        if plan.task_note:
            s["task_losses"] = []
        s["distill"] = [_term(p) for p in group]
        stages[f"student_{names}"] = s
    return {"schema_version": 1, "name": plan.name, "seed": 0,
            "data": {"dataset": plan.dataset, **({"params": plan.data_params} if plan.data_params else {})},
            "stages": stages}


def _made_taps(plan: Any, group: list[Proposal]) -> dict[str, dict[str, Any]]:
    """The recipe taps the terms read that init made (a bird's-eye map of a voxel tap), per side."""
    out: dict[str, dict[str, Any]] = {"student": {}, "teacher": {}}
    for p in group:
        for role, tap in p.taps.items():
            side = "teacher" if role in p.teacher_roles else "student"
            of = plan.facts[side].tap(tap).of
            if of is not None:
                out[side][tap] = {"of": of, "kind": "bev_features", "collapse": "max"}
    return out


def _flow(value: Any) -> str:
    """One value in YAML flow style on one line (strings as JSON, which YAML reads)."""
    if isinstance(value, (str, int, float, bool)) or value is None:  # a scalar: JSON, which YAML reads
        return json.dumps(value)
    return yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=1 << 30).strip()


def term_comment(p: Proposal) -> str:
    """Which taps a term pairs and how (``completion <- completion: sparse_features, 32x32x4 <- 16x16x2 (teacher
    coarser x2), 32 <- 64 ch``), its connector, and any note."""
    parts = [pair.text() for pair in p.pairs.values()]
    if p.connector and "connector" not in p.note:
        parts.append(f"connector {p.connector}: the student's channels projected to the teacher's")
    if p.note:
        parts.append(p.note)
    return "; ".join(parts)


def recipe_text(plan: Any, data: dict[str, Any], argv: list[str]) -> str:
    """``data`` (:func:`recipe_dict`) as YAML with a header (the command, the models, their taps, the pairs) and a
    comment on each term; loading it gives ``data`` back (checked)."""
    lines = [f"# written by: distilkit init {shlex.join(argv)}".rstrip()] + (
        [f"# the teacher: {plan.teacher_checkpoint} (trained; its weights are read when a student runs)"]
        if plan.teacher_checkpoint else []) + [
             f"# teacher: {plan.models['teacher'][0]} · student: {plan.models['student'][0]} · data: {plan.dataset}"
             + (f", grid {plan.grid_text}" if plan.grid_text else ""),
             "# taps (model tap: kind, channels, size):"]
    used = {(side, tap) for p in plan.chosen for role, tap in p.taps.items()
            for side in ["teacher" if role in p.teacher_roles else "student"]}
    for facts in (plan.facts["teacher"], plan.facts["student"]):
        for t in facts.taps:  # the declared taps, and the maps init made that a term reads
            if t.of is None or (facts.role, t.tap) in used:
                ch = t.channels if t.channels is not None else "?"
                made = f" (made: {t.of} collapsed over height by max)" if t.of else ""
                lines.append(f"#   {facts.role} {t.tap}: {t.kind}, {ch} ch, {t.size()}{made}")
    pairs = [p for p in plan.pairs if (p.student.of is None and p.teacher.of is None)
             or {("student", p.student.tap), ("teacher", p.teacher.tap)} <= used]
    lines.append("# pairs (student <- teacher):" if pairs else "# pairs: none (no tap of one kind aligns)")
    lines += [f"#   {p.text()}" for p in pairs]
    lines += [f"# {WEIGHTS_NOTE}"] + ([f"# {plan.task_note} (and no baseline stage)"] if plan.task_note else [])
    lines.append("")
    body = [f"{key}: {_flow(value)}" for key, value in data.items() if key not in ("data", "stages")]
    body += ["data:"] + [f"  {key}: {_flow(value)}" for key, value in data["data"].items()]
    body += ["", "stages:"]
    comments = {p.objective: term_comment(p) for p in plan.chosen}
    for name, stage in data["stages"].items():
        body.append(f"  {name}:")
        for key, value in stage.items():
            if key != "distill":
                body.append(f"    {key}: {_flow(value)}")
                continue
            body.append("    distill:")
            for term in value:
                comment = comments.get(term["name"], "")
                body.append(f"      - {_flow(term)}" + (f"  # {comment}" if comment else ""))
        body.append("")
    text = "\n".join(lines + body).rstrip() + "\n"
    if yaml.safe_load(text) != data:
        from distilkit.pairing.inputs import InitError

        raise InitError("the recipe's YAML does not read back as written (a bug: please report it with the command)")
    return text


__all__ = ["WEIGHTS_NOTE", "recipe_dict", "recipe_text", "term_comment"]
