"""What every command module of ``distilkit`` shares: a subcommand's parser with its examples after the options, and
the ``--set PATH=VALUE`` overrides. Importing it does not import torch."""

from __future__ import annotations

import argparse
import re
import textwrap
from typing import Any


class ExamplesFormatter(argparse.RawDescriptionHelpFormatter):
    """argparse's help with the text after the options (the examples, a list of choices) kept as written where it
    fits the terminal and wrapped where it does not: an example's ``# comment`` goes on the line above it, a command
    too long for one line goes on with ``\\`` (an option kept with its value, the continuation indented, so that it
    still pastes into a shell), a ``NAME  description`` line goes on under its description, and a group's heading
    wraps too."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n".join(out for line in text.splitlines() for out in _fit(line, max(width, 40), indent))

    def start_section(self, heading: str | None) -> None:
        if heading and len(heading) + 1 > self._width - self._current_indent:
            heading = "\n".join(textwrap.wrap(heading, max(self._width - self._current_indent - 1, 40)))
        super().start_section(heading)


_EXAMPLE = re.compile(r"^(\s*)(distilkit\b.*?)(?:\s{2,}(#.*))?$")
_ENTRY = re.compile(r"^(\s*\S+\s{2,})(\S.*)$")


def _fit(line: str, width: int, indent: str) -> list[str]:
    """``line`` as lines of at most ``width`` characters (one that cannot be broken stays whole)."""
    line = indent + line
    if len(line) <= width:
        return [line]
    example = _EXAMPLE.match(line)
    if example:
        lead, cmd, comment = example.groups()
        above = [lead + comment] if comment else []
        return above + _shell_lines(cmd, lead, width)
    entry = _ENTRY.match(line)
    if entry and len(entry.group(1)) < width // 2:
        return textwrap.wrap(entry.group(2), width, initial_indent=entry.group(1),
                             subsequent_indent=" " * len(entry.group(1)), break_on_hyphens=False) or [line]
    lead = line[:len(line) - len(line.lstrip())]
    return textwrap.wrap(line.strip(), width, initial_indent=lead, subsequent_indent=lead + "  ",
                         break_on_hyphens=False) or [line]


def _shell_lines(cmd: str, lead: str, width: int) -> list[str]:
    """A shell command on lines of at most ``width`` characters, each but the last ending in `` \\``, the next
    indented four more: broken between words (a quoted word is one), an option and its value kept together."""
    words = re.findall(r"(?:'[^']*'|\"[^\"]*\"|\S)+", cmd)
    # an option and the value after it are one unit
    units: list[str] = []
    for word in words:
        if units and units[-1].startswith("-") and " " not in units[-1] and not word.startswith("-") and \
                "=" not in units[-1]:
            units[-1] += " " + word
        else:
            units.append(word)
    lines, current, pad = [], lead, lead
    for unit in units:
        if current.strip() and len(current) + 1 + len(unit) + 2 > width:
            lines.append(current + " \\")
            pad = lead + "    "
            current = pad + unit
        else:
            current = current + (" " if current.strip() else "") + unit
    return lines + [current]


def command(sub: Any, name: str, help: str, examples: list[str], *, before: str = "") -> argparse.ArgumentParser:
    """Subcommand ``name`` of ``sub``, its ``examples`` (and ``before`` them, e.g. a list of choices) after the
    options, wrapped to the terminal's width (:class:`ExamplesFormatter`)."""
    text = (before + "\n\n" if before else "") + "examples:\n" + "\n".join(f"  {line}" for line in examples)
    return sub.add_parser(name, help=help, epilog=text, formatter_class=ExamplesFormatter)


def overrides(args: argparse.Namespace) -> dict[str, object] | None:
    """``--set PATH=VALUE ...`` as path -> value, and ``--threads N`` as the recipe's ``threads`` (None without
    any)."""
    threads = getattr(args, "threads", None)
    if not args.set and threads is None:
        return None
    from distilkit.recipe import parse_overrides

    out = parse_overrides(args.set) if args.set else {}
    return {**out, "threads": threads} if threads is not None else out


def threads_option(parser: argparse.ArgumentParser) -> None:
    """``--threads N``: the CPU threads each process computes with (the recipe's ``threads``)."""
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="CPU threads each process computes with (the recipe's threads; default: OMP_NUM_THREADS, "
                             "else SLURM_CPUS_PER_TASK, else the CPUs this process may use)")


def set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set PATH=VALUE ...``: recipe fields overridden by dotted path (validated like the file)."""
    parser.add_argument("--set", nargs="+", action="extend", metavar="PATH=VALUE", default=None, help=help)


__all__ = ["ExamplesFormatter", "command", "overrides", "set_option", "threads_option"]
