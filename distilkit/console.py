"""A rich console that stays readable when output is not a terminal (CI logs, pipes)."""

from __future__ import annotations

import shutil
from typing import Any


def make_console(quiet: bool = False, **kwargs: Any) -> Any:
    from rich.console import Console

    console = Console(quiet=quiet, **kwargs)
    if not console.is_terminal:
        console = Console(quiet=quiet, width=max(shutil.get_terminal_size((160, 24)).columns, 160), **kwargs)
    return console
