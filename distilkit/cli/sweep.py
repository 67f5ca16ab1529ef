"""``distilkit sweep FILE``: variants of a stage (distillation methods, weights, any override) over seeds, in
parallel processes, and their comparison table."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "sweep": ["distilkit sweep recipes/sweeps/quickstart_methods.yaml --jobs 2",
              "distilkit sweep recipes/sweeps/scpnet_table4.yaml --plan             # commands for a cluster",
              "distilkit sweep recipes/sweeps/quickstart_methods.yaml --launcher slurm --partition gpu --gpus-per-run 1 "
              "--time 8:00:00 --slurm account=mylab",
              "distilkit sweep recipes/sweeps/hassc.yaml --launcher slurm --plan   # what it would queue",
              "distilkit sweep recipes/sweeps/quickstart_methods.yaml --status",
              "distilkit sweep recipes/sweeps/quickstart_methods.yaml --seeds auto --target-width 3 --jobs 2"],
}


def add(sub: Any) -> None:
    w = command(sub, "sweep", "compare variants of a stage (distillation methods, weights, any override) over seeds: "
                              "mean ± std, paired differences with 95 %% intervals", EXAMPLES["sweep"])
    w.add_argument("sweep", help="sweep YAML file (see recipes/sweeps/)")
    w.add_argument("--output", "-o", default="runs", help="output folder (default: runs/)")
    w.add_argument("--seeds", type=_seed, nargs="+", default=None, metavar="N",
                   help="override the sweep's seeds; `auto`: add seeds in rounds until every method's corrected "
                        "interval is narrower than --target-width (or --max-seeds have run)")
    w.add_argument("--target-width", type=float, default=None, metavar="W", help="with --seeds auto: the widest "
                   "simultaneous 95 %% interval accepted, in the table's units (mIoU points for SSC)")
    w.add_argument("--max-seeds", type=int, default=20, metavar="N", help="with --seeds auto: at most N seeds "
                   "(default 20)")
    w.add_argument("--seed-step", type=int, default=2, metavar="N", help="with --seeds auto: seeds added a round "
                   "(default 2)")
    w.add_argument("--jobs", "-j", type=int, default=1, metavar="N",
                   help="runs in N parallel processes, the CPU's threads split between them (default: 1)")
    w.add_argument("--plan", action="store_true", help="run, submit and wait for nothing: print one `distilkit run` "
                   "command per run (upstream stages first; their recipes written to OUTPUT/SWEEP/recipes) for a "
                   "cluster scheduler, or with --launcher slurm the jobs, arrays, afterok dependencies and sbatch "
                   "scripts a submission would queue (nothing written); `distilkit sweep` afterwards collects")
    w.add_argument("--collect", action="store_true", help="train nothing: the table of the runs finished so far")
    w.add_argument("--reuse", nargs="+", action="extend", default=None, metavar="DIR",
                   help="folders of another sweep's runs (its output folder, or its records under results/): each "
                   "finished run there with the configuration hash a run here needs is copied in under this sweep's "
                   "name instead of trained (a paper's table drawn from a larger comparison)")
    w.add_argument("--status", action="store_true", help="run nothing: where the sweep stands. Run here: every run "
                   "done, running, stopped (a checkpoint, no process) or waiting, as a grid of variants x seeds, and "
                   "when the rest should end at the pace so far (ask from another terminal while it runs). Queued "
                   "on Slurm: one line per submitted run, pending, running, done or failed, its job id and log")
    w.add_argument("--quiet", "-q", action="store_true", help="no progress bars or per-run lines; the final table is "
                   "still printed")
    s = w.add_argument_group("on a Slurm cluster (pip install 'distilkit[slurm]'; the sweep file's launcher: block "
                             "gives the same, these win)")
    s.add_argument("--launcher", choices=("local", "slurm"), default="local",
                   help="local: parallel processes here (default); slurm: every run queued at once, upstream first")
    s.add_argument("--gpus-per-run", type=int, default=None, metavar="N", help="GPUs of one run (> 1: DDP)")
    s.add_argument("--cpus-per-run", type=int, default=None, metavar="N", help="CPUs of one run (its threads)")
    s.add_argument("--mem", default=None, help="memory of one run (sbatch --mem, e.g. 32G)")
    s.add_argument("--time", default=None, help="a job's time limit (minutes or D-HH:MM:SS; default 4 h): a run "
                   "that needs longer is requeued from its checkpoint")
    s.add_argument("--partition", default=None, help="Slurm partition")
    s.add_argument("--slurm", nargs="+", action="extend", default=None, metavar="KEY=VALUE",
                   help="any other sbatch option, e.g. --slurm account=mylab qos=high constraint=a100")
    s.add_argument("--array-parallelism", type=int, default=None, metavar="N", help="runs of one array at a time")
    s.add_argument("--wait", action="store_true", help="after submitting (or alone), show progress until every job "
                   "has ended, then collect the table")
    w.set_defaults(fn=sweep)


def _seed(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a seed is an integer or `auto`, got {text!r}") from None


def sweep(args: argparse.Namespace) -> int:
    from distilkit.errors import DistilkitError
    from distilkit.sweep.runner import run_sweep

    if args.seeds is not None and "auto" in args.seeds:
        if args.seeds != ["auto"] or args.target_width is None:
            raise DistilkitError("--seeds auto: give `auto` alone, with --target-width W (the widest corrected "
                                 "interval accepted, in the table's units)")
        if args.plan or args.launcher != "local" or args.status or args.wait or args.collect:
            raise DistilkitError("--seeds auto runs locally: it decides each round from the runs finished so far "
                                 "(not with --plan, --collect, --status, --wait or --launcher slurm)")
        from distilkit.sweep.adaptive import run_until_clear

        run_until_clear(args.sweep, args.output, args.jobs, args.target_width, args.max_seeds, args.seed_step,
                        args.quiet)
        return 0
    if args.target_width is not None:
        raise DistilkitError("--target-width goes with --seeds auto")
    cluster = {"gpus": args.gpus_per_run, "cpus": args.cpus_per_run, "mem": args.mem, "time": args.time,
               "partition": args.partition, "array_parallelism": args.array_parallelism, "extra": args.slurm}
    run_sweep(args.sweep, args.output, seeds=args.seeds, jobs=args.jobs, plan=args.plan, collect=args.collect,
              quiet=args.quiet, launcher=args.launcher, cluster=cluster, status=args.status, wait=args.wait,
              reuse=args.reuse)
    return 0
