"""The parser that reference/cli.md documents (``.. argparse:: :module: _cli :func: parser``): distilkit's own
(:func:`distilkit.cli.build_parser`), with each command's text after its options (the examples, a list of choices)
made a literal block, laid out as ``--help`` prints it. sphinx-argparse reads that text as reStructuredText
otherwise, which runs the example lines together into one paragraph."""

from __future__ import annotations

import argparse
import textwrap


def parser() -> argparse.ArgumentParser:
    from distilkit.cli import build_parser

    top = build_parser()

    def literal(p: argparse.ArgumentParser) -> None:
        if p.epilog:
            p.epilog = "::\n\n" + textwrap.indent(p.epilog, "   ")
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for child in action.choices.values():
                    literal(child)

    literal(top)
    return top
