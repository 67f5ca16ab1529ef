"""``distilkit report RUN...`` and ``distilkit compare A B``: stage runs' reports re-rendered, two runs side by
side."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "report": ["distilkit report runs/quickstart                                # every stage of a recipe",
               "distilkit report runs                                          # every run under a folder",
               "distilkit report runs/quickstart/student_dskd-*"],
    "compare": ["distilkit compare runs/quickstart/student-* runs/quickstart/student_dskd-*"],
}


def add(sub: Any) -> None:
    rp = command(sub, "report", "re-render a stage run's report.md and plots (or every run under a folder)",
                 EXAMPLES["report"])
    rp.add_argument("run", nargs="+", help="stage run folders (runs/<recipe>/<stage>-<hash>), or folders of runs at "
                    "any depth (a recipe's or a sweep's output folder, runs/): every finished stage run under them")
    rp.set_defaults(fn=report)
    cp = command(sub, "compare", "two stage runs side by side: configuration, scores, per-class, plots",
                 EXAMPLES["compare"])
    cp.add_argument("run_a", help="the first stage run folder (runs/<recipe>/<stage>-<hash>): the reference, A")
    cp.add_argument("run_b", help="the second stage run folder, B (differences are B - A)")
    cp.add_argument("--out", "-o", default=None, help="folder for compare.md / compare.png "
                                                      "(default: compare-<A>-vs-<B> beside run A)")
    cp.set_defaults(fn=compare)


def report(args: argparse.Namespace) -> int:
    from distilkit.report.run import report_targets, write_run_report

    targets = [run_dir for path in args.run for run_dir in report_targets(path)]  # every folder checked first
    for run_dir in dict.fromkeys(targets):
        print(write_run_report(run_dir))
    return 0


def compare(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.report.compare import compare_runs

    print(compare_runs(args.run_a, args.run_b, args.out, console=make_console()))
    return 0
