"""Exceptions that carry a user-facing message (no traceback is shown for these)."""

from __future__ import annotations


class DistilkitError(Exception):
    """Base class: the CLI prints the message and exits with status 2."""


class RecipeError(DistilkitError):
    """A recipe problem, with the dotted YAML path of each field that is wrong."""

    def __init__(self, problems: list[tuple[str, str]], source: str = "recipe") -> None:
        self.problems = problems
        self.source = source
        lines = [f"{path}: {msg}" if path else msg for path, msg in problems]
        super().__init__(f"{source}: " + ("\n  ".join(lines) if len(lines) == 1 else "\n  " + "\n  ".join(lines)))


class UnknownNameError(DistilkitError, KeyError):
    """A registry lookup failed; the message suggests close matches."""

    def __str__(self) -> str:  # KeyError would add quotes
        return str(self.args[0])


class TapError(DistilkitError):
    """An objective asked for a tap the adapter does not provide (or of the wrong kind)."""


class DataError(DistilkitError):
    """A data file or folder is missing, truncated or malformed."""


class NonFiniteLossError(DistilkitError):
    """A loss term became NaN or infinite during training."""


class GridMismatchError(DistilkitError):
    """Two voxel grids that an objective must align cannot be aligned (no integer factor)."""


class RunLockedError(DistilkitError):
    """Another distilkit process is writing to the same output folder."""


class PluginError(DistilkitError):
    """distilkit's own components (the built-in adapters) failed to load: the installation is broken."""
