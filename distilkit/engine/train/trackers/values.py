"""What a tracker logs, by key: the step's training values (``train/<key>``), an evaluation's scores
(``val/<key>``, a per-class score as ``val/<key>/<class>``, its timing as ``time/val_<key>``), the final scores
(``test/best/<key>``, ...), and the same read back from ``metrics.jsonl`` (the record of the run) for a resume."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any


def flatten(data: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings as ``a/b/c`` keys (lists stay values)."""
    if not isinstance(data, dict):
        return {prefix: data}
    out: dict[str, Any] = {}
    for key, value in data.items():
        out.update(flatten(value, f"{prefix}/{key}" if prefix else str(key)))
    return out


def numbers(values: dict[str, Any]) -> dict[str, float]:
    """The numeric values (numbers and one-element tensors; not booleans, strings or mappings) as floats."""
    out = {}
    for key, value in values.items():
        if isinstance(value, (bool, str, bytes, dict, list, tuple)) or value is None:
            continue
        try:
            out[key] = float(value)
        except (TypeError, ValueError, RuntimeError):
            continue
    return out


TIMINGS = frozenset({"seconds_per_sample"})  # what an evaluation reports besides its scores: how long it took


def _label(name: str) -> str:
    """A class name as a key's last part (letters, digits, ``_-. `` kept; ``/`` would nest it)."""
    return re.sub(r"[^\w\-. ]", "_", str(name))


def score_values(scores: dict[str, Any], where: str, per_class: dict[str, list[str]]) -> dict[str, float]:
    """An evaluation's scores as a tracker logs them: ``<where>/<key>`` for each numeric score, a per-class score
    (``per_class``: its key -> the class of each entry) as ``<where>/<key>/<class>``, a timing (``TIMINGS``) as
    ``time/<where>_<key>`` (``/`` in ``where`` as ``_``): not a score."""
    out: dict[str, Any] = {}
    for key, value in scores.items():
        if isinstance(value, (list, tuple)) and key in per_class:
            out.update({f"{where}/{key}/{_label(c)}": v for c, v in zip(per_class[key], value)})
        elif key.rpartition(".")[2] in TIMINGS:
            out[f"time/{where.replace('/', '_')}_{key}"] = value
        else:
            out[f"{where}/{key}"] = value
    return numbers(out)


def final_values(summary: dict[str, Any], per_class: dict[str, list[str]] | None = None) -> dict[str, Any]:
    """A finished stage's scores as summary values: ``test/best/<key>`` and ``test/last/<key>`` on the report
    split (per class and timings as :func:`score_values`), ``best_val/<key>`` at the best validation step,
    ``best_step``, ``steps``, ``report_split``."""
    per_class = per_class or {}
    test = summary.get("test") or {}
    best = summary.get("best") or {}
    out: dict[str, Any] = {}
    for which in ("best", "last"):
        out.update(score_values(test.get(which) or {}, f"test/{which}", per_class))
    out.update({k: v for k, v in score_values(best.get("scores") or {}, "best_val", per_class).items()
                if not k.startswith("time/")})  # the validation's timing at that step: no final value
    out.update({"best_step": best.get("step"), "steps": summary.get("steps"),
                "report_split": summary.get("report_split")})
    return {k: v for k, v in out.items() if v is not None}


def kept_values(run_dir: Path, after: int, upto: int, every: int, total: int,
                per_class: dict[str, list[str]]) -> dict[int, dict[str, float]]:
    """What ``metrics.jsonl`` (the record of the run) holds for the steps after ``after`` up to ``upto``, as a
    tracker logs it: ``train/<key>`` at the tracker's steps (every ``every`` and the last, ``total``) and the
    validation scores (:func:`score_values`) at each evaluation."""
    try:
        lines = (run_dir / "metrics.jsonl").read_text(encoding="utf-8").splitlines()
    except OSError:
        return {}
    out: dict[int, dict[str, float]] = {}
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:  # a line cut by a kill
            continue
        step = record.get("step") if isinstance(record, dict) and "event" not in record else None
        if not isinstance(step, int) or not after < step <= upto:
            continue
        if isinstance(record.get("eval"), dict):
            out.setdefault(step, {}).update(score_values(record["eval"], "val", per_class))
        elif "eval" not in record and (step % every == 0 or step == total):
            values = {k: v for k, v in record.items() if k not in ("step", "epoch", "time")}
            out.setdefault(step, {}).update({f"train/{k}": v for k, v in numbers(values).items()})
    return out


__all__ = ["TIMINGS", "final_values", "flatten", "kept_values", "numbers", "score_values"]
