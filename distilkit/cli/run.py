"""``distilkit run RECIPE``: train, distill and evaluate the stages of a recipe (over several seeds, or in several
processes with torchrun)."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command, overrides, set_option, threads_option

EXAMPLES = {
    "run": ["distilkit run recipes/quickstart.yaml",
            "distilkit run recipes/quickstart.yaml --set 'stages.*.train.steps=4'   # every stage, 4 steps",
            "distilkit run recipes/scorelidar.yaml --seed 0 1 2                    # mean ± std over seeds",
            "distilkit run recipes/quickstart.yaml --set 'trackers=[tensorboard, mlflow]'   # experiment trackers"],
}


def add(sub: Any) -> None:
    r = command(sub, "run", "train, distill and evaluate the stages of a recipe", EXAMPLES["run"])
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
    set_option(r, "override recipe fields by dotted path (as sweep files do), e.g. --set "
                  "stages.student.optimizer.lr=0.01 (values are read as YAML); validated like the file")
    threads_option(r)
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
    r.set_defaults(fn=run)


def run(args: argparse.Namespace) -> int:
    import os

    from distilkit.engine.train import stop

    stop.install()  # SIGTERM (or the death of the sweep that started it) stops after a step, its checkpoint written
    if args.nproc_per_node is not None and "LOCAL_RANK" not in os.environ:
        from distilkit.engine.train.distributed import refuse_more_processes_than_gpus
        from distilkit.engine.train.launch import launch

        # before torchrun starts anything: N processes need N GPUs where a stage trains on CUDA
        refuse_more_processes_than_gpus(args.nproc_per_node, _devices(args), f"--nproc-per-node {args.nproc_per_node}")
        return launch(_forwarded(args), args.nproc_per_node, args.nnodes, args.node_rank, args.master_addr,
                      args.master_port)
    _start_world(args)
    if args.seed is not None and len(args.seed) > 1:
        from distilkit.engine.train.seeds import run_seeds

        run_seeds(args.recipe, args.output, args.seed, baseline=args.baseline, quiet=args.quiet, rerun=args.rerun,
                  only=args.stage, wait=not args.no_wait, overrides=overrides(args))
        return _finished()
    if args.baseline is not None:
        from distilkit.errors import DistilkitError

        raise DistilkitError("--baseline compares stages over several seeds: give them, e.g. --seed 0 1 2")
    from distilkit.engine.train.pipeline import Pipeline

    pipe = Pipeline(args.recipe, args.output, quiet=args.quiet, seed=args.seed[0] if args.seed else None,
                    overrides=overrides(args))
    pipe.run(stop_after=args.stop_after, rerun=args.rerun, only=args.stage, wait=not args.no_wait)
    return _finished()


def _devices(args: argparse.Namespace) -> dict[str, Any]:
    """The device each stage this run trains on (``--stage``: those and the stages they need), read off the
    recipe with its ``--set`` overrides."""
    from distilkit.engine.assemble.devices import stage_devices
    from distilkit.recipe import load_recipe

    return stage_devices(load_recipe(args.recipe, overrides(args)), args.stage)


def _start_world(args: argparse.Namespace) -> None:
    """In a process of a multi-process run (torchrun's, or a Slurm step's tasks): its process group, started for
    the devices its stages train on — NCCL and a GPU per process where one trains on CUDA (more processes on the
    node than GPUs is refused, naming both), gloo over the host where all train on the CPU
    (:func:`~distilkit.engine.train.distributed.world_from_env`). A single process: nothing."""
    import os

    from distilkit.engine.train.distributed import from_slurm, world_from_env

    from_slurm()
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        world_from_env(_devices(args))


def _forwarded(args: argparse.Namespace) -> list[str]:
    """The arguments each of torchrun's processes is started with (``distilkit run`` less the launcher's own)."""
    return [args.recipe, "--output", args.output, *(["--quiet"] if args.quiet else []),
            *(["--no-wait"] if args.no_wait else []), *(["--seed", *map(str, args.seed)] if args.seed else []),
            *(["--baseline", args.baseline] if args.baseline else []), *(["--rerun", *args.rerun] if args.rerun else []),
            *(["--stage", *args.stage] if args.stage else []), *(["--set", *args.set] if args.set else []),
            *(["--threads", str(args.threads)] if args.threads is not None else []),
            *(["--stop-after", str(args.stop_after)] if args.stop_after is not None else [])]


def _finished() -> int:
    """0 for a finished run; a process of a multi-process run leaves here, once all are done
    (:func:`~distilkit.engine.train.distributed.leave`)."""
    from distilkit.engine.train.distributed import leave, world_from_env

    leave(world_from_env())
    return 0
