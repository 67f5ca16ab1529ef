"""A finished stage's ``summary.json``, read without importing torch (a sweep's plan and collection ask which runs
are finished)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


def read_summary(run_dir: Path) -> dict[str, Any] | None:
    """A finished stage's summary (None: not finished)."""
    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return summary if summary.get("status") == "finished" else None


__all__ = ["read_summary"]
