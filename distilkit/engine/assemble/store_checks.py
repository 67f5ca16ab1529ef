"""What ``validate`` checks of ``teacher.store`` (issue 58): that a store can hold what the stage reads, and that a
lossy layout keeps every value the stage's terms read; and of ``teacher.control`` (issue 59): that the control
reaches every use of the teacher (each refusal one line naming why)."""

from __future__ import annotations

from typing import Any

from distilkit.taps import DENSE_GRID_KINDS as GRID_KINDS

_KEPT = {"all": {"all", "valid", "occupied"}, "valid": {"valid", "occupied"}, "occupied": {"occupied"}}


def store_problems(spec: Any, distill: list[Any], teacher: Any, info: Any, path: str) -> list[tuple[str, str]]:
    """``teacher.store`` where a store could not hold what the stage reads: a teacher that changes (its own moving
    average, one in train mode), a continuous augmentation (no finite set of transforms to store), a term that
    calls the teacher itself, nothing read; and a lossy layout that drops what a term reads."""
    store = spec.teacher.store if spec.teacher is not None else None
    if store is None or not distill:  # no term: the teacher does not run (a sweep's undistilled variant keeps
        return []                     # the sweep's setting)
    where = f"{path}.teacher.store"
    if spec.teacher.ema is not None:
        return [(where, "the stage's own moving average changes at every step: its outputs cannot be stored")]
    out = []
    if spec.teacher.mode == "train":
        out.append((where, "a teacher in mode: train (batch statistics, dropout) gives other outputs at every "
                           "forward: they cannot be stored; use mode: eval or a live teacher"))
    augment = spec.train.augment
    if augment is not None and augment.continuous:
        out.append((where, "train.augment draws continuous transforms (rotate, tilt, scale): no finite set of "
                           "transforms to store the teacher under; the stage runs its teacher live without "
                           "`store`"))
    for i, term in enumerate(distill):
        if term.card.REQUIRES:
            out.append((where, f"distill[{i}] ({term.name}) calls the teacher's {', '.join(sorted(term.card.REQUIRES))}"
                               "(): it needs the teacher itself, not its stored outputs"))
    read = [tap for t in distill for role, tap in t.taps.items() if role in t.card.TEACHER_ROLES]
    if not read and not out:
        out.append((where, "no distillation term of the stage reads a teacher tap: there is nothing to store"))
    kinds = teacher.taps if teacher is not None else {}
    return out + layout_problems(store, distill, kinds, info, where)


def mask_labels(distill: list[Any], kinds: dict[str, str]) -> set[str]:
    """The label fields by which the terms that read a dense teacher tap on a grid choose their voxels (each one's
    ``target`` field, default ``voxel_target``): a masked store keeps the voxels of one of them."""
    return {term.fields.get("target", "voxel_target") for term in distill for role, tap in term.taps.items()
            if role in term.card.TEACHER_ROLES and kinds.get(tap) in GRID_KINDS}


def layout_problems(store: Any, distill: list[Any], kinds: dict[str, str], info: Any,
                    where: str) -> list[tuple[str, str]]:
    """A lossy layout that would drop what a term reads: ``voxels`` narrower than a term's reads of a dense teacher
    tap on a grid (:meth:`~distilkit.cards.base.TermCard.teacher_voxels`), ``topk`` for a term that reads more than
    the teacher's softmax (:meth:`~distilkit.cards.base.TermCard.teacher_softmax`), or keeping every class."""
    out: list[tuple[str, str]] = []
    classes = getattr(info, "num_classes", None) if info is not None else None
    if store.topk is not None and classes is not None and store.topk >= classes:
        out.append((f"{where}.topk", f"topk {store.topk} keeps every one of the data's {classes} classes: leave topk "
                                     "out (the exact layout)"))
    labels = mask_labels(distill, kinds) if store.voxels != "all" else set()
    for i, term in enumerate(distill):
        voxels = term.card.teacher_voxels(term.params)
        softmax = term.card.teacher_softmax(term.params)
        for role, tap in term.taps.items():
            if role not in term.card.TEACHER_ROLES:
                continue
            kind = kinds.get(tap)
            if store.voxels != "all" and kind in GRID_KINDS:
                reads = voxels.get(role, "all")
                if reads not in _KEPT[store.voxels]:
                    out.append((f"{where}.voxels", f"distill[{i}] ({term.name}) reads the teacher's {tap!r} at "
                                                   f"{reads} voxels; a store of the {store.voxels} voxels drops some "
                                                   f"of them (use voxels: {reads}, or a live teacher)"))
            if store.topk is not None and kind == "voxel_logits" and role not in softmax:
                out.append((f"{where}.topk", f"distill[{i}] ({term.name}) reads the teacher's {tap!r} scores "
                                             "themselves, not only through their softmax: a top-k store keeps "
                                             f"{store.topk} of every class's scores (leave topk out)"))
    if len(labels) > 1:
        out.append((f"{where}.voxels", f"the terms choose their voxels by different labels ({', '.join(sorted(labels))}):"
                                       " a masked store keeps one set"))
    return out


def control_problems(spec: Any, distill: list[Any], path: str) -> list[tuple[str, str]]:
    """``teacher.control: shuffled`` where a term calls the teacher itself (on the sample's own input: the control
    would not reach it), or where no term reads a teacher tap (nothing to shuffle)."""
    if spec.teacher is None or spec.teacher.control != "shuffled" or not distill:
        return []
    where = f"{path}.teacher.control"
    out = [(where, f"distill[{i}] ({t.name}) calls the teacher's {', '.join(sorted(t.card.REQUIRES))}() on the "
                   "sample's own input: the shuffled control gives another sample's outputs to the terms that read "
                   "teacher taps only; use control: random") for i, t in enumerate(distill) if t.card.REQUIRES]
    if not out and not any(role in t.card.TEACHER_ROLES for t in distill for role in t.taps):
        out.append((where, "no distillation term of the stage reads a teacher tap: there is nothing to shuffle"))
    return out


__all__ = ["control_problems", "layout_problems", "mask_labels", "store_problems"]
