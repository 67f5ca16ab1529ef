"""The ``distilkit`` command: run | sweep | report | compare | validate | init | list | schema | bench | eval | predict |
export | complete | data — one module per command group (the user's view of it: arguments, help, examples), each
calling into the library.

Importing this package and ``distilkit --help`` do not import torch; each command imports what it needs. A user's
mistake (bad recipe, missing file, NaN loss) prints one clear message and exits with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from distilkit.cli import bench, components, data, infer, init, reports, run, sweep, validate
from distilkit.cli.bench import BENCH_NAMES

# the command groups, in the order `distilkit --help` lists their commands
GROUPS = (run, sweep, reports, validate, init, components, bench, infer, data)

# every command's examples (shown after its options; a test runs them against the parser)
EXAMPLES: dict[str, list[str]] = {name: lines for group in GROUPS for name, lines in group.EXAMPLES.items()}


def build_parser() -> argparse.ArgumentParser:
    from distilkit import __version__

    p = argparse.ArgumentParser(prog="distilkit", description="Knowledge distillation for 3D semantic scene completion.")
    p.add_argument("--version", action="version", version=f"distilkit {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for group in GROUPS:
        group.add(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)  # `import distilkit` set the libraries' reproducibility before torch
    try:
        code = int(args.fn(args) or 0)
        sys.stdout.flush()  # here, not at exit: a reader gone away is one of the cases below
        return code
    except BrokenPipeError:  # the reader of the output went away (`distilkit sweep --plan ... | head`): stop quietly
        _drop_stdout()
        return 1  # as rich's console does when its own write meets the closed pipe
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


def _drop_stdout() -> None:
    """Point standard output at /dev/null, so the interpreter's flush at exit does not fail a second time."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


__all__ = ["BENCH_NAMES", "EXAMPLES", "build_parser", "main"]
