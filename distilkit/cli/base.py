"""What every command module of ``distilkit`` shares: a subcommand's parser with its examples after the options, and
the ``--set PATH=VALUE`` overrides. Importing it does not import torch."""

from __future__ import annotations

import argparse
from typing import Any


def command(sub: Any, name: str, help: str, examples: list[str], *, before: str = "") -> argparse.ArgumentParser:
    """Subcommand ``name`` of ``sub``, its ``examples`` (and ``before`` them, e.g. a list of choices) after the
    options."""
    text = (before + "\n\n" if before else "") + "examples:\n" + "\n".join(f"  {line}" for line in examples)
    return sub.add_parser(name, help=help, epilog=text, formatter_class=argparse.RawDescriptionHelpFormatter)


def overrides(args: argparse.Namespace) -> dict[str, object] | None:
    """``--set PATH=VALUE ...`` as path -> value (None without any)."""
    if not args.set:
        return None
    from distilkit.recipe import parse_overrides

    return parse_overrides(args.set)


def set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set PATH=VALUE ...``: recipe fields overridden by dotted path (validated like the file)."""
    parser.add_argument("--set", nargs="+", action="extend", metavar="PATH=VALUE", default=None, help=help)


__all__ = ["command", "overrides", "set_option"]
