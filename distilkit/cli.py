"""The ``distilkit`` command: run | sweep | report | compare | validate | list | schema | bench | eval | predict | export
| data | complete.

Importing this module and ``distilkit --help`` do not import torch; each command imports what
it needs. A user's mistake (bad recipe, missing file, NaN loss) prints one clear message and
exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence


def _launch(args: argparse.Namespace) -> int:
    """``distilkit run ... --nproc-per-node N``: the same command in N processes per node, started by PyTorch's
    elastic launcher (torchrun), each with its share of the CPU's threads."""
    import os
    import subprocess

    from distilkit.errors import DistilkitError

    n, nodes = args.nproc_per_node, args.nnodes
    if n < 1 or nodes < 1:
        raise DistilkitError(f"--nproc-per-node and --nnodes must be at least 1, got {n} and {nodes}")
    rest = [args.recipe, "--output", args.output, *(["--quiet"] if args.quiet else []),
            *(["--no-wait"] if args.no_wait else []), *(["--seed", *map(str, args.seed)] if args.seed else []),
            *(["--baseline", args.baseline] if args.baseline else []), *(["--rerun", *args.rerun] if args.rerun else []),
            *(["--stage", *args.stage] if args.stage else []), *(["--set", *args.set] if args.set else []),
            *(["--stop-after", str(args.stop_after)] if args.stop_after is not None else [])]
    where = (["--standalone"] if nodes == 1 else
             [f"--nnodes={nodes}", f"--node-rank={args.node_rank}", f"--master-addr={args.master_addr}",
              f"--master-port={args.master_port}"])
    from distilkit.engine.train.cpus import usable_cpus

    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", str(max(1, usable_cpus() // n)))}
    cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc-per-node={n}", *where, "-m", "distilkit", "run",
           *rest]
    return subprocess.call(cmd, env=env)


def _cmd_run(args: argparse.Namespace) -> int:
    import os

    from distilkit.engine.train import stop

    stop.install()  # SIGTERM (or the death of the sweep that started it) stops after a step, its checkpoint written
    if args.nproc_per_node is not None and "LOCAL_RANK" not in os.environ:
        return _launch(args)
    if args.seed is not None and len(args.seed) > 1:
        from distilkit.engine.train.seeds import run_seeds

        run_seeds(args.recipe, args.output, args.seed, baseline=args.baseline, quiet=args.quiet, rerun=args.rerun,
                  only=args.stage, wait=not args.no_wait, overrides=_overrides(args))
        return _finished()
    if args.baseline is not None:
        from distilkit.errors import DistilkitError

        raise DistilkitError("--baseline compares stages over several seeds: give them, e.g. --seed 0 1 2")
    from distilkit.engine.train.pipeline import Pipeline

    pipe = Pipeline(args.recipe, args.output, quiet=args.quiet, seed=args.seed[0] if args.seed else None,
                    overrides=_overrides(args))
    pipe.run(stop_after=args.stop_after, rerun=args.rerun, only=args.stage, wait=not args.no_wait)
    return _finished()


def _finished() -> int:
    """0 for a finished run; a process of a multi-process run leaves here, once all are done
    (:func:`~distilkit.engine.train.distributed.leave`)."""
    from distilkit.engine.train.distributed import leave, world_from_env

    leave(world_from_env())
    return 0


def _overrides(args: argparse.Namespace) -> dict[str, object] | None:
    """``--set PATH=VALUE ...`` as path -> value (None without any)."""
    if not args.set:
        return None
    from distilkit.recipe import parse_overrides

    return parse_overrides(args.set)


def _cmd_sweep(args: argparse.Namespace) -> int:
    from distilkit.sweep.runner import run_sweep

    run_sweep(args.sweep, args.output, seeds=args.seeds, jobs=args.jobs, plan=args.plan, collect=args.collect,
              quiet=args.quiet)
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from distilkit.report.run import report_targets, write_run_report

    for run_dir in report_targets(args.run):
        print(write_run_report(run_dir))
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.report.compare import compare_runs

    print(compare_runs(args.run_a, args.run_b, args.out, console=make_console()))
    return 0


def _cmd_validate(args: argparse.Namespace) -> int:
    from distilkit.engine.assemble.checks import data_problems, weights_problems
    from distilkit.engine.assemble.resolve import resolve
    from distilkit.errors import RecipeError
    from distilkit.recipe import load_recipe
    from distilkit.registry import DATASETS

    overrides = _overrides(args)
    for path in args.recipes:
        res = resolve(load_recipe(path, overrides), str(path))
        entry = DATASETS.entry(res.recipe.data.dataset)
        has_split = lambda split: bool(entry.meta.get("has_split", lambda p, s: s != "test")(  # noqa: E731
            res.data_params, split))
        unreadable = data_problems(res, has_split)
        problems = unreadable + weights_problems(res)  # what the run needs: its data and its weights files
        if problems:
            if unreadable and not args.no_memory:
                print("memory not estimated: the data cannot be read", file=sys.stderr)
            raise RecipeError(problems, str(path))
        stages = ", ".join(
            f"{n} ({s.student.adapter}" + "".join(f"; {edge} <- {up}" for edge, up in s.spec.edges().items())
            + (f"; {', '.join(t.name for t in s.distill)}" if s.distill else "") + ")"
            for n, s in res.stages.items())
        print(f"{path}: ok — {len(res.stages)} stage(s): {stages}")
        for line in _networks(res):
            print(f"  {line}")
        if not args.no_memory:
            _validate_memory(res)
    return 0


def _networks(res: Any) -> list[str]:
    """One line per distinct model of the recipe: its adapter and whether it is the paper's network or a stand-in."""
    seen: dict[str, list[str]] = {}
    for name, stage in res.stages.items():
        spec = stage.student
        what = spec.cls.network(spec.params)
        if what:
            seen.setdefault(f"{spec.adapter}: {what}", []).append(name)
    return [f"model of {', '.join(stages)} — {line}" for line, stages in seen.items()]


def _validate_memory(res: Any) -> None:
    """Each training stage's memory per step (two steps at small sizes, scaled), with a warning where it does not
    fit in what the machine has free."""
    from distilkit.console import make_console
    from distilkit.engine.memory.estimate import estimate_stage

    console = make_console()
    for name in res.order:
        try:
            with console.status(f"stage {name}: two training steps at a small size, to estimate its memory"):
                estimate = estimate_stage(res, name)
        except Exception as exc:  # the estimate is advice: a probe that fails must not fail validation
            console.print(f"[yellow]stage {name}: memory not estimated ({type(exc).__name__}: {exc})[/]")
            continue
        if estimate is None:
            continue
        print(f"  {estimate.line()}")
        warning = estimate.warning()
        if warning:
            stage = res.stages[name]
            console.print(f"[yellow]warning:[/] {warning}: lower train.batch_size (now {estimate.batch_size}), the "
                          f"grid (data.params.scale) or the size of {stage.student.adapter}'s model", highlight=False,
                          soft_wrap=True)


def _cmd_list(args: argparse.Namespace) -> int:
    from rich.table import Table

    from distilkit.console import make_console

    from distilkit.registry import ALL_REGISTRIES, plugin_errors

    if args.markdown:
        if args.kind not in ("objectives", "datasets"):
            from distilkit.errors import DistilkitError

            raise DistilkitError("--markdown is available for `distilkit list objectives` and `list datasets`")
        from distilkit.schema_doc import datasets_markdown, objectives_markdown

        print(objectives_markdown() if args.kind == "objectives" else datasets_markdown())
        return 0
    console = make_console()
    for kind, reg in ALL_REGISTRIES.items():
        if args.kind and args.kind != kind.split()[0].rstrip("s") and args.kind != kind:
            continue
        if kind == "adapters" and console.width < 120:  # six columns do not read at 80: one block per adapter
            _print_adapter_blocks(console, reg)
            continue
        table = Table(title=kind, title_justify="left")
        table.add_column("name", style="bold")
        table.add_column("description")
        table.add_column("paper")
        table.add_column(_LIST_COLUMN[kind])
        if kind == "adapters":
            table.add_column("parameters (default)")
            table.add_column("network (by size)")
        for e in reg:
            also = reg.aliases_of(e.name)
            extra = [_params_cell(e.obj.Params), _networks_cell(e.obj)] if kind == "adapters" else []
            table.add_row(e.name + (f" (also {', '.join(also)})" if also else ""), e.description, e.paper,
                          _list_cell(kind, e), *extra)
        console.print(table)
    for msg in plugin_errors:
        console.print(f"[yellow]warning:[/] {msg}")
    return 0


def _print_adapter_blocks(console: Any, reg: Any) -> None:
    """``distilkit list adapters`` on a narrow console: each adapter's fields as a two-column table."""
    from rich.table import Table

    console.print("adapters")
    for e in reg:
        also = reg.aliases_of(e.name)
        block = Table(title=e.name + (f" (also {', '.join(also)})" if also else ""), title_justify="left",
                      title_style="bold", show_header=False, expand=True)
        block.add_column("field", style="dim", no_wrap=True)
        block.add_column("value", ratio=1)
        for field, value in (("description", e.description), ("paper", e.paper),
                             (_LIST_COLUMN["adapters"], _list_cell("adapters", e)),
                             ("parameters", _params_cell(e.obj.Params).replace("\n", ", ")),
                             ("network", _networks_cell(e.obj))):
            block.add_row(field, value)
        console.print(block)


_LIST_COLUMN = {"adapters": "taps (name: kind)", "objectives": "reads (tap kinds)", "task losses": "reads (tap kinds)",
                "datasets": "batch fields", "metrics": "scores (tap kind)", "optimizers": "—",
                "schedules": "parameters", "connectors": "—", "hooks": "parameters",
                "recorders": "—"}


def _params_cell(params: Any) -> str:
    """An adapter's parameters with their defaults, one per line (docs/recipe-reference.md has their descriptions)."""
    import json

    out = []
    for name, field in params.model_fields.items():
        default = field.get_default(call_default_factory=True)
        out.append(f"{name}={json.dumps(default, default=str)}")
    return "\n".join(out) or "—"


def _networks_cell(adapter: Any) -> str:
    """What each size of an adapter builds: the paper's network or a CPU stand-in."""
    networks = getattr(adapter, "NETWORKS", {})
    if "" in networks:
        return networks[""]
    return "\n".join(f"{size}: {what}" for size, what in networks.items()) or "—"


def _list_cell(kind: str, entry: object) -> str:
    """What ``distilkit list`` shows of a component: an adapter's taps by name and kind, the tap kinds a term reads,
    the batch fields a dataset provides (from its default parameters), what a metric scores."""
    obj, meta = getattr(entry, "obj"), getattr(entry, "meta")
    if kind == "adapters" and getattr(obj, "TAPS", None):
        return ", ".join(f"{name}: {k}" for name, k in obj.TAPS.items())
    if kind == "datasets" and "info" in meta and "params" in meta:
        try:  # a dataset with required parameters (a root folder) still shows what its defaults give
            fields = meta["info"](meta["params"].model_construct()).fields
        except Exception:
            return "—"
        return ", ".join(sorted(fields))
    if kind in ("schedules", "hooks") and "params" in meta:
        return ", ".join(meta["params"].model_fields) or "—"
    return ", ".join(getattr(entry, "consumes")) or "—"


def _cmd_schema(args: argparse.Namespace) -> int:
    from distilkit.schema_doc import recipe_json_schema, recipe_reference_markdown

    print(recipe_reference_markdown() if args.markdown else recipe_json_schema())
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from distilkit.bench import run_bench

    run_bench(args.names, device=args.device, quick=args.quick)
    return 0


EXAMPLES: dict[str, list[str]] = {
    "run": ["distilkit run recipes/quickstart.yaml",
            "distilkit run recipes/quickstart.yaml --set 'stages.*.train.steps=4'   # every stage, 4 steps",
            "distilkit run recipes/scorelidar.yaml --seed 0 1 2                    # mean ± std over seeds"],
    "sweep": ["distilkit sweep recipes/sweeps/quickstart_methods.yaml --jobs 2",
              "distilkit sweep recipes/sweeps/scpnet_table4.yaml --plan             # commands for a cluster"],
    "report": ["distilkit report runs/quickstart                                # every stage of a recipe",
               "distilkit report runs/quickstart/student_dskd-*"],
    "compare": ["distilkit compare runs/quickstart/student-* runs/quickstart/student_dskd-*"],
    "validate": ["distilkit validate recipes/quickstart.yaml",
                 "distilkit validate recipes/semantickitti_scpnet.yaml --set data.params.root=/data/semantickitti"],
    "list": ["distilkit list objectives", "distilkit list task_losses", "distilkit list objectives --markdown"],
    "schema": ["distilkit schema > recipe.schema.json                       # editor completion",
               "distilkit schema --markdown > docs/recipe-reference.md"],
    "bench": ["distilkit bench dskd pkt", "distilkit bench --quick", "distilkit bench determinism loader"],
    "eval": ["distilkit eval --dataset-root /data/semantickitti --predictions preds --split valid"],
    "predict": ["distilkit predict runs/NAME/STAGE-* --dataset-root /data/semantickitti --split valid --out preds",
                "distilkit predict runs/NAME/STAGE-* --dataset-root /data/semantickitti --split test --out submission"],
    "export": ["distilkit export runs/quickstart/student_dskd-* --out student.pt",
               "distilkit export runs/quickstart/student_dskd-* --out student.pt --which last"],
    "data": ["distilkit data export-kitti /tmp/kitti --camera", "distilkit data rectify /data/semantickitti"],
    "data rectify": ["distilkit data rectify /data/semantickitti",
                     "distilkit data rectify /data/semanticposs --labels semanticposs"],
    "data export-kitti": ["distilkit data export-kitti /tmp/kitti",
                          "distilkit data export-kitti /tmp/kitti --camera --set beams=64 azimuth_steps=2048"],
    "complete": ["distilkit complete runs/scorelidar/student-* scan.bin --out scene.ply --steps 8",
                 "distilkit complete runs/scorelidar/student-* scan.bin --out scene.ply --refine "
                 "runs/scorelidar/refined_8-*"],
}

# every `distilkit bench` NAME with what it times (the help lists them without importing torch; a test keeps this
# in step with distilkit.bench.BENCHES)
BENCH_NAMES: dict[str, str] = {
    "dskd": "DSKD's exact O(N C^2) identity against the N x N matrices",
    "pkt": "PKT, blocked, against the dense kernel",
    "rgo2d": "RGO²D, by index_add, against the authors' broadcast masks",
    "kd": "KD over a masked voxel volume",
    "nst": "NST's MMD, by its Gram identity",
    "structural": "ScoreLiDAR's structural loss: key points and the point-wise distance matrices",
    "sampler": "LiDiff's sampler at 8 against 50 steps",
    "guidance": "LiDiff's sampler with classifier-free guidance against without",
    "complete": "`distilkit complete` on a 125,000-point scan, with and without refinement",
    "determinism": "a training step with the deterministic settings on and off",
    "loader": "an epoch of the quickstart teacher's steps with 2 loader workers and with none",
    "camera": "the camera student's step with and without RGO²D",
    "kitti": "reading, fusing and evaluating SemanticKITTI-sized frames",
    "sparse": "a Cylinder3D-sized submanifold 3x3x3 layer (GFLOP/s vs sgemm) against dense conv3d",
    "networks": "each family's network at size tiny and paper: parameters, a training step's time and memory",
}


def _doc(name: str) -> dict[str, Any]:
    """A subcommand's help layout: its examples (and, for bench, every benchmark) after the options."""
    text = "examples:\n" + "\n".join(f"  {line}" for line in EXAMPLES[name])
    if name == "bench":
        text = "benchmarks:\n" + "\n".join(f"  {n:<12} {d}" for n, d in BENCH_NAMES.items()) + "\n\n" + text
    return {"epilog": text, "formatter_class": argparse.RawDescriptionHelpFormatter}


def build_parser() -> argparse.ArgumentParser:
    from distilkit import __version__

    p = argparse.ArgumentParser(prog="distilkit", description="Knowledge distillation for 3D semantic scene completion.")
    p.add_argument("--version", action="version", version=f"distilkit {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    r = sub.add_parser("run", **_doc("run"), help="train, distill and evaluate the stages of a recipe")
    r.add_argument("recipe", help="recipe YAML file")
    r.add_argument("--output", "-o", default="runs", help="output folder (default: runs/)")
    r.add_argument("--quiet", "-q", action="store_true", help="no progress bars or tables")
    r.add_argument("--rerun", nargs="+", metavar="STAGE", help="retrain these stages (and the stages that use "
                   "them as teacher) even if finished; the previous runs are kept beside the new ones")
    r.add_argument("--seed", type=int, nargs="+", default=None, metavar="N",
                   help="override the recipe's seed; several seeds run one after another (each its own run) and "
                        "end in a table of mean ± std over the seeds, written to seeds.md")
    r.add_argument("--baseline", metavar="STAGE", default=None,
                   help="with several seeds: the stage the paired differences are taken to (default: the first "
                        "stage without distillation that is nobody's teacher)")
    r.add_argument("--stage", nargs="+", metavar="STAGE", default=None,
                   help="run only these stages and the stages they need (their teacher, their initial weights)")
    r.add_argument("--set", nargs="+", action="extend", metavar="PATH=VALUE", default=None,
                   help="override recipe fields by dotted path (as sweep files do), e.g. --set "
                        "stages.student.optimizer.lr=0.01 (values are read as YAML); validated like the file")
    r.add_argument("--no-wait", action="store_true",
                   help="stop with an error instead of waiting when another distilkit run is training a stage")
    d = r.add_argument_group("multi-process training (PyTorch's torchrun; gloo on the CPU, NCCL on GPUs)")
    d.add_argument("--nproc-per-node", type=int, default=None, metavar="N",
                   help="train each stage in N processes on this node, train.batch_size being the global batch")
    d.add_argument("--nnodes", type=int, default=1, metavar="M", help="nodes taking part (default 1)")
    d.add_argument("--node-rank", type=int, default=0, help="this node's rank (0 .. M-1)")
    d.add_argument("--master-addr", default="127.0.0.1", help="address of node 0")
    d.add_argument("--master-port", type=int, default=29500, help="free port on node 0")
    r.add_argument("--stop-after", type=int, default=None, metavar="STEPS", help=argparse.SUPPRESS)
    r.set_defaults(fn=_cmd_run)
    w = sub.add_parser("sweep", **_doc("sweep"), help="compare variants of a stage (distillation methods, weights, any override) "
                                     "over seeds: mean ± std, paired differences with 95 %% intervals")
    w.add_argument("sweep", help="sweep YAML file (see recipes/sweeps/)")
    w.add_argument("--output", "-o", default="runs", help="output folder (default: runs/)")
    w.add_argument("--seeds", type=int, nargs="+", default=None, metavar="N", help="override the sweep's seeds")
    w.add_argument("--jobs", "-j", type=int, default=1, metavar="N",
                   help="runs in N parallel processes, the CPU's threads split between them (default: 1)")
    w.add_argument("--plan", action="store_true", help="print one `distilkit run` command per run (upstream "
                   "stages first) for a cluster scheduler, run nothing; `distilkit sweep` afterwards collects")
    w.add_argument("--collect", action="store_true", help="train nothing: the table of the runs finished so far")
    w.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
    w.set_defaults(fn=_cmd_sweep)
    rp = sub.add_parser("report", **_doc("report"), help="re-render a stage run's report.md and plots (or every run under a folder)")
    rp.add_argument("run", help="a stage run folder (runs/<recipe>/<stage>-<hash>) or a recipe's output folder")
    rp.set_defaults(fn=_cmd_report)
    cp = sub.add_parser("compare", **_doc("compare"), help="two stage runs side by side: configuration, scores, per-class, plots")
    cp.add_argument("run_a", help="the first stage run folder (runs/<recipe>/<stage>-<hash>): the reference, A")
    cp.add_argument("run_b", help="the second stage run folder, B (differences are B - A)")
    cp.add_argument("--out", "-o", default=None, help="folder for compare.md / compare.png "
                                                      "(default: compare-<A>-vs-<B> beside run A)")
    cp.set_defaults(fn=_cmd_compare)
    v = sub.add_parser("validate", **_doc("validate"), help="check recipes without training (exit status 2 on a problem)")
    v.add_argument("recipes", nargs="+", help="recipe YAML files")
    v.add_argument("--set", nargs="+", action="extend", metavar="PATH=VALUE", default=None,
                   help="override recipe fields by dotted path, e.g. --set stages.student.train.steps=10")
    v.add_argument("--no-memory", action="store_true", help="skip the memory estimate (two training steps of each "
                   "stage at a small size)")
    v.set_defaults(fn=_cmd_validate)
    ls = sub.add_parser("list", **_doc("list"), help="registered adapters, objectives, task losses, datasets, metrics, optimizers, "
                                     "schedules, connectors, hooks and recorders")
    ls.add_argument("kind", nargs="?", metavar="KIND", type=lambda text: text.replace("_", " "),
                    choices=["adapters", "objectives", "task losses", "datasets", "metrics", "optimizers", "schedules",
                             "connectors", "hooks", "recorders"],
                    help="one kind of component: adapters, objectives, task_losses (or 'task losses'), datasets, "
                         "metrics, optimizers, schedules, connectors, hooks, recorders (default: all)")
    ls.add_argument("--markdown", action="store_true",
                    help="objectives or datasets as Markdown (docs/objectives.md, docs/datasets.md)")
    ls.set_defaults(fn=_cmd_list)
    s = sub.add_parser("schema", **_doc("schema"), help="print the recipe JSON schema (for editor completion)")
    s.add_argument("--markdown", action="store_true", help="print the recipe reference as Markdown instead")
    s.set_defaults(fn=_cmd_schema)
    b = sub.add_parser("bench", **_doc("bench"), help="time objectives forward+backward at realistic sizes")
    b.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (listed below; default: all)")
    b.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    b.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    b.set_defaults(fn=_cmd_bench)
    ev = sub.add_parser("eval", **_doc("eval"), help="SemanticKITTI's official completion evaluation of a predictions folder "
                                     "(and VoxFormer's 12.8 / 25.6 m range split)")
    _folder_split_args(ev, "the SemanticKITTI folder (holds sequences/NN/voxels/)", "valid", "08")
    ev.add_argument("--predictions", required=True, help="the folder holding sequences/NN/predictions/*.label")
    ev.add_argument("--out", default=None, help="where to write the scores (default: PREDICTIONS/scores.txt)")
    ev.add_argument("--classes", default="semantickitti", choices=["semantickitti", "semanticposs"],
                    help="the labels' class table and official splits (semanticposs: 11 classes, valid = test = 02)")
    ev.set_defaults(fn=_cmd_eval)
    pr = sub.add_parser("predict", **_doc("predict"), help="write a trained SSC run's predictions of a SemanticKITTI folder in the "
                                        "submission format (sequences/NN/predictions/NNNNNN.label)")
    pr.add_argument("run", help="a stage's run folder or checkpoint (trained on a semantickitti folder)")
    _folder_split_args(pr, "the SemanticKITTI folder to predict", "test", "11-21")
    pr.add_argument("--out", required=True, help="the folder to write sequences/NN/predictions/ into")
    pr.add_argument("--device", default="cpu", help="cpu or cuda")
    pr.set_defaults(fn=_cmd_predict)
    xp = sub.add_parser("export", **_doc("export"), help="write a trained student's weights alone (a plain state dict "
                                                         "for torch.load(weights_only=True) or `init: {checkpoint: "
                                                         "...}`) and a JSON of its adapter, parameters and classes")
    xp.add_argument("run", help="a stage's run folder (runs/<recipe>/<stage>-<hash>) or a checkpoint file")
    xp.add_argument("--out", "-o", required=True, help="the weights file to write (e.g. student.pt); the JSON goes "
                                                      "beside it (student.json)")
    xp.add_argument("--which", default="best", choices=["best", "last"],
                    help="the run folder's checkpoint: the best validation score (default) or the last step")
    xp.set_defaults(fn=_cmd_export)
    dp = sub.add_parser("data", **_doc("data"), help="work on data folders: rectify a SemanticKITTI folder's completion labels, "
                                     "export synthetic streets as one")
    dsub = dp.add_subparsers(dest="data_command", required=True, metavar="ACTION",
                             help="rectify (SCPNet's label rectification) or export-kitti (synthetic streets as a folder)")
    rect = dsub.add_parser("rectify", **_doc("data rectify"), help="SCPNet's label rectification: write sequences/NN/voxels_rectified/ "
                                           "beside the original voxel labels (which stay untouched)")
    rect.add_argument("root", help="a SemanticKITTI folder (holds sequences/)")
    rect.add_argument("--sequences", nargs="+", default=None, help="the sequences (default: every one)")
    rect.add_argument("--classes", nargs="+", default=None,
                      help="dynamic classes (default SemanticKITTI: car truck other-vehicle person bicyclist "
                           "motorcyclist)")
    rect.add_argument("--out", default="voxels_rectified", help="the folder written in each sequence")
    rect.add_argument("--labels", default="semantickitti", choices=["semantickitti", "semanticposs"],
                      help="the folder's class table (semanticposs: people, rider and car by default)")
    rect.set_defaults(fn=_cmd_data_rectify)
    ex = dsub.add_parser("export-kitti", **_doc("data export-kitti"), help="write synthetic streets as a SemanticKITTI folder (scans, panoptic "
                                              "labels, voxels, invalid and occluded masks, poses, calibration, "
                                              "with --camera images)")
    ex.add_argument("out", help="the folder to write (sequences/ goes inside)")
    ex.add_argument("--sequences", nargs="+", default=["00", "08"], help="sequence names (default: 00 08)")
    ex.add_argument("--frames", type=int, default=16, help="scans per sequence (default 16)")
    ex.add_argument("--stride", type=int, default=5, help="voxel labels every n-th scan (SemanticKITTI: 5)")
    ex.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="synthetic-lidar parameters, e.g. beams=64 azimuth_steps=2048 gt_frames=10 seed=1 "
                         "'camera={height: 96, width: 320}'")
    ex.add_argument("--camera", action="store_true",
                    help="also render image_2/ (the synthetic camera's defaults unless --set camera=... says more)")
    ex.set_defaults(fn=_cmd_data_export)
    c = sub.add_parser("complete", **_doc("complete"), help="complete a scan (.bin, .ply, .npy) into a dense scene with a trained "
                                        "point-diffusion model")
    c.add_argument("checkpoint", help="a checkpoint (best.pt / last.pt) or a stage's run folder")
    c.add_argument("scan", help="the scan: SemanticKITTI .bin, .ply or .npy")
    c.add_argument("--out", "-o", required=True, help="where to write the scene (.ply, .npy or .bin)")
    c.add_argument("--steps", type=int, default=None, help="sampler steps (default: the model's sample_steps)")
    c.add_argument("--guidance", type=float, default=None, help="classifier-free guidance weight (default: the model's)")
    c.add_argument("--scan-points", type=int, default=None,
                   help="points the scan is sampled to (default: what the model was trained with)")
    c.add_argument("--seed", type=int, default=0, help="seed of the sampler's noise")
    c.add_argument("--refine", default=None, metavar="RUN",
                   help="refine the completion with this refinement run (a lidiff-refine stage's folder or checkpoint)")
    c.add_argument("--device", default="cpu", help="cpu or cuda")
    c.set_defaults(fn=_cmd_complete)
    return p


def _folder_split_args(parser: argparse.ArgumentParser, root_help: str, split: str, split_sequences: str) -> None:
    """``--dataset-root``, and ``--split`` (an official split) or ``--sequences`` (eval and predict)."""
    parser.add_argument("--dataset-root", required=True, help=root_help)
    parser.add_argument("--split", default=split, choices=["train", "valid", "test"],
                        help=f"the official split's sequences (default {split} = {split_sequences})")
    parser.add_argument("--sequences", nargs="+", default=None, help="these sequences instead of the split's")


def _cmd_eval(args: argparse.Namespace) -> int:
    import yaml
    from rich.table import Table

    from distilkit.console import make_console, progress_bar
    from distilkit.files import atomic_write_text
    from distilkit.data.info import ClassTable
    from distilkit.data.params import KITTI_SPLITS, POSS_SPLITS
    from distilkit.metrics.official import evaluate_folder, scores_yaml

    console = make_console()
    poss = args.classes == "semanticposs"
    sequences = args.sequences or list((POSS_SPLITS if poss else KITTI_SPLITS)[args.split])
    table = ClassTable.semanticposs() if poss else ClassTable.semantickitti()
    with progress_bar(console, "eval") as advance:
        ev = evaluate_folder(args.dataset_root, args.predictions, sequences, advance, table)
    table = Table(title=f"SemanticKITTI completion, sequences {' '.join(sequences)}, {ev.frames} frames (%)")
    for col in ("box", "IoU", "precision", "recall", "mIoU"):
        table.add_column(col, justify="left" if col == "box" else "right")
    for name, s in (("51.2 m (whole grid)", ev.scores), *((f"{r:g} m", v) for r, v in sorted(ev.ranges.items(),
                                                                                             reverse=True))):
        table.add_row(name, *(f"{100 * s[k]:.2f}" for k in ("iou", "precision", "recall", "miou")))
    console.print(table)
    console.print("  ".join(f"{n} {100 * v:.1f}" for n, v in zip(ev.names[1:], ev.scores["class_iou"])))
    out = Path(args.out) if args.out else Path(args.predictions) / "scores.txt"
    atomic_write_text(out, yaml.safe_dump(scores_yaml(ev), sort_keys=False))
    console.print(f"scores: {out}")
    return 0


def _cmd_predict(args: argparse.Namespace) -> int:
    from distilkit.console import make_console, progress_bar
    from distilkit.engine.infer.predict import predict_folder

    console = make_console()
    with progress_bar(console, "predict") as advance:
        n, sequences = predict_folder(args.run, args.dataset_root, args.sequences or args.split, args.out, args.device,
                                      advance)
    console.print(f"{n} frames of sequences {' '.join(sequences)} predicted into {args.out}/sequences/*/predictions/")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.engine.infer.export import export_student

    done = export_student(args.run, args.out, args.which)
    make_console().print(f"{done.weights}: the {done.adapter} student's {done.tensors} tensors (step {done.step}), a "
                         f"plain state dict; {done.sidecar}: its adapter, parameters, data and classes")
    return 0


def _cmd_data_rectify(args: argparse.Namespace) -> int:
    from distilkit.console import make_console, progress_bar
    from distilkit.data.info import ClassTable
    from distilkit.data.rectify import rectify_folder

    console = make_console()
    table = ClassTable.semanticposs() if args.labels == "semanticposs" else ClassTable.semantickitti()
    with progress_bar(console, "rectifying") as advance:
        counts = rectify_folder(args.root, args.sequences, args.classes, args.out, advance, table)
    for name, (before, left) in counts.items():
        share = f"{100 * left / before:.1f} % left" if before else "none"
        console.print(f"{name}: {left:,} of {before:,} voxels left ({share})")
    console.print(f"written to sequences/*/{args.out}/ under {args.root}")
    return 0


def _cmd_data_export(args: argparse.Namespace) -> int:
    import yaml
    from pydantic import ValidationError

    from distilkit.console import make_console, progress_bar
    from distilkit.data.export import export_kitti
    from distilkit.data.params import SyntheticParams
    from distilkit.errors import DistilkitError

    values = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            raise DistilkitError(f"--set {item!r}: expected KEY=VALUE")
        values[key] = yaml.safe_load(value)
    if args.camera and values.get("camera") is None:
        values["camera"] = {}
    try:
        params = SyntheticParams(**values)
    except ValidationError as err:
        raise DistilkitError(f"--set: {err.errors()[0]['loc'][0]}: {err.errors()[0]['msg']}") from None
    console = make_console()
    with progress_bar(console, "export-kitti") as advance:
        root = export_kitti(args.out, params, args.sequences, args.frames, args.stride, advance)
    console.print(f"{root}: sequences {' '.join(args.sequences)}, {args.frames} scans each, voxel labels every "
                  f"{args.stride}th")
    return 0


def _cmd_complete(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.engine.infer.complete import complete

    console = make_console()
    with console.status("loading the model") as spinner:
        done = complete(args.checkpoint, args.scan, args.out, steps=args.steps, guidance=args.guidance,
                        scan_points=args.scan_points, seed=args.seed, device=args.device,
                        status=lambda text: spinner.update(text), refine=args.refine)
    console.print(f"{done.out}: {done.output_points:,} points completed from {done.input_points:,} scan points "
                  f"(sampled to {done.scan_points:,}) in {done.steps} steps{', refined' if done.refined else ''}, "
                  f"{done.seconds:.1f} s")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)  # `import distilkit` set the libraries' reproducibility before torch
    try:
        return int(args.fn(args) or 0)
    except KeyboardInterrupt:
        print("stopped; finished stages and the last checkpoint are kept (run the same command again to resume)",
              file=sys.stderr)
        return 130
    except Exception as exc:
        from distilkit.errors import DistilkitError

        if isinstance(exc, DistilkitError):
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if isinstance(exc, OSError) and exc.filename is not None:  # the machine's: a read-only folder, a full disk
            hint = " (a read-only folder? give --output a writable one)" if isinstance(exc, PermissionError) else ""
            print(f"error: {exc.filename}: {exc.strerror or exc}{hint}", file=sys.stderr)
            return 2
        raise


if __name__ == "__main__":
    raise SystemExit(main())
