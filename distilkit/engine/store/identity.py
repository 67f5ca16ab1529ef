"""A stage's identity: the hash that names its run folder (``<stage>-<hash>``), so a finished stage is reused and a
changed one retrains.

It hashes what produces the stage and nothing else, without special cases:

* the **non-default values** of its resolved configuration (every pydantic model dumped without its defaults:
  a field added to the schema later, at its default, leaves every identity as it was) — the resolved terms with
  their weights, taps and the batch fields a recipe points elsewhere than the term's default, the optimizer's
  parameter groups, the adapter's parameters;
* the **code versions** that produce it (distilkit's, the dataset's, each component's ``VERSION``);
* a **fingerprint of the data**, not the path where it lies: a dataset registers ``fingerprint`` (SemanticKITTI:
  the names, sizes and modification times of its files), else its parameters stand for it (a generator's); a
  generator's **field groups** (the streets' camera) count only for the stages that read their fields
  (:func:`stage_reads`): adding a camera, or changing its code, retrains the camera's users and nothing else;
* the identities of the stages it reads (:meth:`~distilkit.recipe.StageSpec.edges`), and the content of
  weights files it reads.

What only changes how a run is watched or how fast it goes (labels, logging and checkpoint intervals, hooks, the
device, loader workers) is left out.
:func:`stage_config` is the full record written to ``recipe.resolved.yaml``; :func:`stage_identity` is what is
hashed.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from distilkit import __version__
from distilkit.registry import DATASETS

# fields of a stage that do not change what is trained
NOT_IDENTITY = {"label": True, "seed": True, "train": {"log_every", "checkpoint_every", "device", "workers", "hooks"}}


def file_digest(path: str) -> str:
    """SHA-256 of a file's content (``missing:<path>`` when there is none)."""
    p = Path(path).expanduser()
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else f"missing:{path}"


def _dump(model: BaseModel, full: bool, **kwargs: Any) -> dict[str, Any]:
    return model.model_dump(mode="json", by_alias=True, exclude_defaults=not full, **kwargs)


def stage_seed(res: Any, stage: Any) -> int:
    """The seed a stage trains with: its own, else the recipe's."""
    return stage.spec.seed if stage.spec.seed is not None else res.recipe.seed


def stage_reads(res: Any, stage: Any) -> frozenset[str]:
    """The batch fields a stage reads: its models' inputs (student, teacher, auxiliary models), its terms' batch
    fields, its metrics' targets and its labels edge."""
    models = [stage.student, stage.teacher, *(aux.model for aux in stage.aux)]
    out = {f for m in models if m is not None for f in m.card.inputs(m.params)}
    out |= {f for t in (*stage.task_losses, *stage.distill) for f in t.fields.values()}
    out |= {f for m in stage.metrics for f in m.card.TARGETS}
    labels = stage.spec.labels
    if labels is not None:
        out |= {f for f in (labels.field, labels.keep) if f is not None}
    return frozenset(out)


def field_groups(res: Any, stage: Any) -> tuple[dict[str, int], set[str]]:
    """The dataset's field groups (:class:`~distilkit.data.info.FieldGroup`) this stage reads, with their versions,
    and the names of those it does not read (their parameters are left out of its identity)."""
    groups = DATASETS.entry(res.recipe.data.dataset).meta.get("field_groups", {})
    reads = stage_reads(res, stage)
    used = {name: g.version for name, g in groups.items() if g.fields & reads}
    return used, set(groups) - set(used)


def code_versions(res: Any, stage: Any) -> dict[str, Any]:
    """The code versions that produce a stage: a change in any of them retrains exactly its users (a field group's
    version only the stages that read its fields)."""
    ds = DATASETS.entry(res.recipe.data.dataset)
    out: dict[str, Any] = {
        "distilkit": __version__,
        "dataset": ds.meta.get("version", 1),
        **({"fields": used} if (used := field_groups(res, stage)[0]) else {}),
        "adapter": getattr(stage.student.card, "VERSION", 1),
        "task_losses": {t.name: getattr(t.card, "VERSION", 1) for t in stage.task_losses},
        "distill": {t.name: getattr(t.card, "VERSION", 1) for t in stage.distill},
    }
    if stage.ema is not None:
        out["ema_teacher"] = 1  # the moving average's code (engine.train.ema): raise when what it computes changes
    elif stage.teacher is not None and stage.teacher_from is None:  # a checkpoint teacher: its adapter's code
        out["teacher_adapter"] = getattr(stage.teacher.card, "VERSION", 1)
    return out


def data_fingerprint(res: Any, stage: Any) -> dict[str, Any]:
    """What identifies the data: the dataset's registered name and its ``fingerprint(params)`` (a folder's files),
    or its non-default parameters (a generator's) but those of field groups the stage does not read."""
    entry = DATASETS.entry(res.recipe.data.dataset)
    fingerprint = entry.meta.get("fingerprint")
    if fingerprint is not None:
        return {"dataset": entry.name, **fingerprint(res.data_params)}
    return {"dataset": entry.name, "params": _dump(res.data_params, False, exclude=field_groups(res, stage)[1] or None)}


def _fields(term: Any, fields: frozenset[str], full: bool) -> dict[str, str]:
    """A term's batch fields (``full=False``: those a recipe points elsewhere than the term's default)."""
    return dict(term.fields) if full else {role: name for role, name in term.fields.items()
                                           if name != term.card.default_field(role, fields)}


def _terms(terms: list[Any], full: bool, fields: frozenset[str]) -> list[dict[str, Any]]:
    return [{"name": t.name, "weight": t.weight, "params": _dump(t.params, full), "taps": t.taps,
             "fields": _fields(t, fields, full), "connector": t.connector, "warmup_steps": t.warmup_steps}
            for t in terms]


def _files(spec: Any) -> dict[str, str]:
    """Digests of the weights files a stage reads (a checkpoint teacher, init from a file)."""
    return {field: file_digest(src.checkpoint) for field, src in (("teacher", spec.teacher), ("init", spec.init))
            if src is not None and src.checkpoint is not None}


def stage_config(res: Any, stage: Any, hashes: dict[str, str], full: bool = True) -> dict[str, Any]:
    """The stage as it will be trained: its recipe fields, the resolved model and terms, the data, the code
    versions, the seed and the identities of the stages it reads. ``full=False``: only the non-default values of
    what changes the trained result (:func:`stage_identity`)."""
    spec = stage.spec
    fields = _dump(spec, full, exclude=None if full else NOT_IDENTITY)
    for key in ("model", "task_losses", "distill"):  # given below as resolved
        fields.pop(key, None)
    return {
        **fields,
        "versions": code_versions(res, stage),
        "seed": stage_seed(res, stage),
        "data": ({"dataset": DATASETS.entry(res.recipe.data.dataset).name, "params": _dump(res.data_params, True)}
                 if full else data_fingerprint(res, stage)),
        "model": {"adapter": stage.student.adapter, "params": _dump(stage.student.params, full),
                  "taps": {n: _dump(h, full) for n, h in stage.student.hooks.items()}},
        "task_losses": _terms(stage.task_losses, full, res.data_info.fields),
        "distill": _terms(stage.distill, full, res.data_info.fields),
        "param_groups": stage.param_groups,
        "upstream": {field: hashes[name] for field, name in spec.edges().items()},
        "files": _files(spec),
    }


def stage_identity(res: Any, stage: Any, hashes: dict[str, str]) -> str:
    """The 10-hex-digit hash of :func:`stage_config` without defaults."""
    config = stage_config(res, stage, hashes, full=False)
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:10]


def stage_hashes(res: Any) -> tuple[dict[str, str], dict[str, dict[str, Any]]]:
    """Each stage's identity (in dependency order, so upstream identities are known) and its full record."""
    hashes: dict[str, str] = {}
    configs: dict[str, dict[str, Any]] = {}
    for name in res.order:
        hashes[name] = stage_identity(res, res.stages[name], hashes)
        configs[name] = stage_config(res, res.stages[name], hashes)
    return hashes, configs


__all__ = ["code_versions", "data_fingerprint", "field_groups", "file_digest", "stage_config", "stage_hashes",
           "stage_identity", "stage_reads", "stage_seed"]
