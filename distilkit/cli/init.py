"""``distilkit init``: a recipe for any teacher and student — the taps both models expose, the pairs that align, the
objectives that fit each pair, written as a commented recipe that ``validate`` accepts (then checked as it would
check it). With flags for scripts (``--yes``), numbered choices in a terminal."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Any

from distilkit.cli.base import command, set_option

EXAMPLES = {
    "init": ["distilkit init --teacher js3cnet --student scpnet --yes -o pair.yaml",
             "distilkit init --teacher scpnet --student voxformer --show",
             "distilkit init --teacher scpnet --student scpnet --objectives kd,pkt --yes",
             "distilkit init --teacher voxformer --student voxformer --taps mgd.student=bev_query_features "
             "mgd.teacher=bev_query_features --yes",
             "distilkit init                                                    # asks, with numbered choices, in a terminal"],
}


def add(sub: Any) -> None:
    p = command(sub, "init", "write a recipe for a teacher and a student: their taps, the pairs that align, the "
                "objectives that fit", EXAMPLES["init"])
    p.add_argument("--teacher", metavar="ADAPTER|RUN", help="the teacher's adapter (distilkit list adapters), or a "
                   "trained teacher: a run folder or a checkpoint (its adapter, parameters and data are read from it)")
    p.add_argument("--student", metavar="ADAPTER", help="the student's adapter")
    for role in ("teacher", "student"):
        p.add_argument(f"--{role}-params", nargs="+", action="extend", default=[], metavar="K=V",
                       help=f"the {role}'s model.params, each value read as YAML (size=paper, frames=2)")
    p.add_argument("--dataset", help="the data (distilkit list datasets; default: the first that serves both models)")
    p.add_argument("--data-params", nargs="+", action="extend", default=[], metavar="K=V",
                   help="data.params, each value read as YAML (scale=4, 'camera={height: 24, width: 80}')")
    p.add_argument("--objectives", help="comma-separated objectives, each on its best pair of taps (default: kd on "
                   "the logits, then dskd on sparse features, or fitnets on volumes, or monoocc_image on images)")
    p.add_argument("--taps", nargs="+", action="extend", default=[], metavar="OBJECTIVE.ROLE=TAP",
                   help="the taps an objective reads, instead of its best pair: e.g. `--taps "
                        "fitnets.student=image_features fitnets.teacher=image_features`. The objectives named are "
                        "chosen beside --objectives; without --objectives they are the only ones (no defaults). "
                        "`--show` lists the taps and the pairs that align")
    p.add_argument("--stages", choices=("combined", "each"), default="combined",
                   help="one student stage with every objective (default), or one per objective")
    p.add_argument("--no-baseline", action="store_true", help="no student stage without distillation")
    set_option(p, "override fields of the written recipe by dotted path, e.g. `--set 'stages.*.train.steps=100'`")
    p.add_argument("--show", action="store_true", help="print the taps, pairs and objectives; write nothing")
    p.add_argument("--static", action="store_true", help="run no model: channels from the cards only (equal-width "
                   "objectives get a linear connector), and the written recipe's terms are not run")
    p.add_argument("--no-check", action="store_true", help="write without validating")
    p.add_argument("--yes", "-y", action="store_true", help="take the defaults: no questions")
    p.add_argument("--interactive", action="store_true", help="ask even without a terminal (answers on stdin)")
    p.add_argument("-o", "--output", type=Path, help="where to write (default: ./STUDENT_from_TEACHER.yaml)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --output")
    p.set_defaults(fn=init)


def _pairs(items: list[str], flag: str) -> dict[str, Any]:
    from distilkit.errors import DistilkitError
    from distilkit.recipe import parse_yaml

    out = {}
    for item in items:
        key, eq, text = item.partition("=")
        if not eq or not key.strip():
            raise DistilkitError(f"{flag}: {item!r}: expected K=V, e.g. frames=2")
        out[key.strip()] = parse_yaml(text, f"{flag} {key.strip()}")
    return out


def init(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.errors import DistilkitError
    from distilkit.pairing import plan

    console = make_console()
    ask = args.interactive or (not args.yes and not args.show and sys.stdin.isatty())
    if not ask and not (args.teacher and args.student):
        raise DistilkitError("distilkit init: give --teacher and --student (and --yes), or run it in a terminal")
    if args.output is not None and args.output.exists() and not args.force and not args.show:
        raise DistilkitError(f"{args.output} exists: give another -o, or --force to overwrite it")
    if ask:
        from distilkit.cli.init_prompts import ask_models

        ask_models(args, console, lambda teacher, student: _dataset_reasons(teacher, student, args))
    objectives = [o.strip() for o in args.objectives.split(",") if o.strip()] if args.objectives else None
    checkpoint, teacher_params = None, _pairs(args.teacher_params, "--teacher-params")
    data_params = _pairs(args.data_params, "--data-params")
    if _is_run(args.teacher):  # a trained teacher: its adapter, parameters and (as the default) its data
        from distilkit.pairing import from_checkpoint

        if teacher_params:
            raise DistilkitError("--teacher-params with a trained teacher: its parameters are its checkpoint's "
                                 "(other ones would not fit its weights)")
        args.teacher, teacher_params, data, checkpoint = from_checkpoint(args.teacher)
        if data and args.dataset in (None, data.get("dataset")):
            args.dataset, data_params = data["dataset"], {**(data.get("params") or {}), **data_params}
        elif data:
            console.print(f"[yellow]note:[/] the teacher was trained on {data['dataset']}, not {args.dataset}",
                          highlight=False)
    elif "/" in args.teacher or args.teacher.endswith((".pt", ".pth")):
        raise DistilkitError(f"--teacher {args.teacher}: no such run folder or checkpoint file")
    with console.status("reading both models' taps (one forward each on a dry batch)" if not args.static else ""):
        p = plan(args.teacher, args.student, teacher_params=teacher_params,
                 student_params=_pairs(args.student_params, "--student-params"), dataset=args.dataset,
                 data_params=data_params, objectives=objectives, static=args.static, taps=_forced(args.taps),
                 require=not (args.show or ask))
    p.teacher_checkpoint = checkpoint
    if args.static:
        if p.found and not p.task_note:
            console.print("[yellow]note:[/] --static: the student's task losses are not checked against the taps "
                          "its forward returns (validate the file before a long run)", highlight=False)
    p.each, p.baseline = args.stages == "each", p.baseline and not args.no_baseline
    from distilkit.cli.init_prompts import show

    if args.show or ask:
        show(p, console)
    if args.show:
        return 0
    if ask:
        from distilkit.cli.init_prompts import ask_choices

        ask_choices(p, args, console)
        if not p.chosen:
            raise DistilkitError("no objective chosen: nothing to write")
    return _write(p, args, console, retry=objectives is None and not args.taps and not ask)


def _forced(items: list[str]) -> dict[str, dict[str, str]]:
    """``--taps OBJECTIVE.ROLE=TAP ...`` as objective -> role -> tap."""
    from distilkit.errors import DistilkitError

    out: dict[str, dict[str, str]] = {}
    for item in items:
        key, eq, tap = item.partition("=")
        objective, dot, role = (part.strip() for part in key.partition("."))
        if not (eq and dot and objective and role and tap.strip()):
            raise DistilkitError(f"--taps: {item!r}: expected OBJECTIVE.ROLE=TAP, e.g. fitnets.student=image_features")
        if role in out.get(objective, {}):
            raise DistilkitError(f"--taps: {objective}.{role} given twice ({out[objective][role]} and {tap.strip()})")
        out.setdefault(objective, {})[role] = tap.strip()
    return out


def _dataset_reasons(teacher: str, student: str, args: argparse.Namespace) -> dict[str, str | None] | None:
    """Each dataset and why it cannot serve both models (:func:`~distilkit.pairing.dataset_reasons`); None where a
    model is not a registered adapter (a trained teacher's run brings its own data; a typo is the plan's to name)."""
    from distilkit.pairing import check_models, dataset_reasons
    from distilkit.registry import ADAPTERS

    if teacher not in ADAPTERS.names() or student not in ADAPTERS.names():
        return None
    models = {"teacher": (teacher, _pairs(args.teacher_params, "--teacher-params")),
              "student": (student, _pairs(args.student_params, "--student-params"))}
    check_models(models)
    return dataset_reasons(models, _pairs(args.data_params, "--data-params"))


def _is_run(teacher: str) -> bool:
    """Whether ``--teacher`` names a run folder or checkpoint file rather than a registered adapter."""
    from distilkit.registry import ADAPTERS, load_plugins

    load_plugins()
    return teacher not in ADAPTERS.names() and Path(teacher).exists()


def _write(p: Any, args: argparse.Namespace, console: Any, retry: bool) -> int:
    from distilkit.errors import DistilkitError
    from distilkit.files import atomic_write_text
    from distilkit.pairing.confirm import confirm
    from distilkit.pairing.write import recipe_dict, recipe_text
    from distilkit.recipe import parse_overrides, set_path

    path = args.output or Path(f"{p.name}.yaml")
    if path.exists() and not args.force:
        raise DistilkitError(f"{path} exists: give another -o, or --force to overwrite it")
    argv = sys.argv[2:] if len(sys.argv) > 2 and sys.argv[1] == "init" else []
    while True:
        data = recipe_dict(p)
        for key, value in (parse_overrides(args.set) if args.set else {}).items():
            set_path(data, key, value, "distilkit init", f"--set {key}")
        atomic_write_text(path, recipe_text(p, data, argv))
        if args.no_check:
            console.print(f"wrote {path} (not validated: --no-check)", highlight=False)
            break
        with console.status(f"validating {path}: the terms on a dry batch" if not args.static else ""):
            problems = confirm(path, run_terms=not args.static)
        failed = {int(m.group(1)) for f, _ in problems for m in [re.search(r"\.distill\[(\d+)\]", f)] if m}
        if problems and retry and failed and len(failed) < len(p.chosen) and not p.each:
            for field, problem in problems:  # a default that fails its first step is dropped, said so
                console.print(f"[yellow]dropped[/] {field}: {problem}", highlight=False, soft_wrap=True)
            p.chosen = [c for i, c in enumerate(p.chosen) if i not in failed]
            retry = False
            continue
        if problems:
            lines = "\n".join(f"  {f}: {msg}" if f else f"  {msg}" for f, msg in problems)
            raise DistilkitError(f"wrote {path}, but it does not validate (fix it, or rerun with other choices and "
                                 f"--force):\n{lines}")
        console.print(f"wrote {path}: validated (the terms ran on a dry batch)" if not args.static else
                      f"wrote {path}: resolved (--static: no term ran)", highlight=False)
        break
    console.print(f"next: distilkit validate {path}   # with the memory estimate\n      distilkit run {path}",
                  highlight=False)
    return 0
