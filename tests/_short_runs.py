"""``python tests/_short_runs.py OUT RECIPE...``: one training step (``distilkit run --stop-after 1``) of each
recipe, one after another in this one process (test_properties starts it with a memory limit, so a runaway
allocation fails here, not in CI). Writes ``OUT/results.json``: per recipe, the exit status ``main`` returned and
what it wrote to stderr; an exception escaping ``main`` (what `python -m distilkit` would print as a traceback) is
recorded as status 1 with its traceback."""

from __future__ import annotations

import json
import os
import sys
import tempfile
import traceback
from pathlib import Path


def _one(recipe: str, out: Path) -> dict:
    from distilkit.cli import main

    with tempfile.TemporaryFile(mode="w+b") as err:
        sys.stderr.flush()
        saved = os.dup(2)
        os.dup2(err.fileno(), 2)  # what the command writes to stderr, at the descriptor (rich, warnings, C code)
        try:
            try:
                status = main(["run", recipe, "-o", str(out), "-q", "--stop-after", "1"])
            except SystemExit as exc:  # as `python -m distilkit` would exit
                status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:  # noqa: BLE001  escaping main: a traceback in a real process
                traceback.print_exc()
                status = 1
            sys.stderr.flush()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        err.seek(0)
        return {"recipe": recipe, "status": status, "stderr": err.read().decode("utf-8", "replace")}


def main_(argv: list[str]) -> None:
    out, recipes = Path(argv[0]), argv[1:]
    results = [_one(r, out / f"runs{i}") for i, r in enumerate(recipes)]
    (out / "results.json").write_text(json.dumps(results))


if __name__ == "__main__":
    main_(sys.argv[1:])
