"""``distilkit sweep FILE``: variants of a stage (distillation methods, weights, any override) over seeds, in
parallel processes, and their comparison table."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "sweep": ["distilkit sweep recipes/sweeps/quickstart_methods.yaml --jobs 2",
              "distilkit sweep recipes/sweeps/scpnet_table4.yaml --plan             # commands for a cluster"],
}


def add(sub: Any) -> None:
    w = command(sub, "sweep", "compare variants of a stage (distillation methods, weights, any override) over seeds: "
                              "mean ± std, paired differences with 95 %% intervals", EXAMPLES["sweep"])
    w.add_argument("sweep", help="sweep YAML file (see recipes/sweeps/)")
    w.add_argument("--output", "-o", default="runs", help="output folder (default: runs/)")
    w.add_argument("--seeds", type=int, nargs="+", default=None, metavar="N", help="override the sweep's seeds")
    w.add_argument("--jobs", "-j", type=int, default=1, metavar="N",
                   help="runs in N parallel processes, the CPU's threads split between them (default: 1)")
    w.add_argument("--plan", action="store_true", help="print one `distilkit run` command per run (upstream "
                   "stages first) for a cluster scheduler, run nothing; `distilkit sweep` afterwards collects")
    w.add_argument("--collect", action="store_true", help="train nothing: the table of the runs finished so far")
    w.add_argument("--quiet", "-q", action="store_true", help="no progress bars")
    w.set_defaults(fn=sweep)


def sweep(args: argparse.Namespace) -> int:
    from distilkit.sweep.runner import run_sweep

    run_sweep(args.sweep, args.output, seeds=args.seeds, jobs=args.jobs, plan=args.plan, collect=args.collect,
              quiet=args.quiet)
    return 0
