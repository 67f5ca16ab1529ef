"""``no_run_reports``: a module-scoped autouse fixture for the modules whose in-process runs' reports (report.md and
its figures) no test reads — tests/test_reports.py tests them. A tiny stage's run report is about a third of its CPU
after the imports, even with conftest's stand-in for the PNG rendering. Import it into the module
(``from _no_run_reports import no_run_reports  # noqa: F401``); `distilkit run` processes a test starts write
theirs, as a user's would. The recipe report (Pipeline.run's) is still written."""

from __future__ import annotations

from typing import Iterator

import pytest


@pytest.fixture(autouse=True, scope="module")
def no_run_reports() -> Iterator[None]:
    import distilkit.report.run

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(distilkit.report.run, "write_run_report", lambda run_dir: None)
        yield
