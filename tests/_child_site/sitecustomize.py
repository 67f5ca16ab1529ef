"""Put on the ``PYTHONPATH`` of the tests' child processes by tests/conftest.py. While ``DISTILKIT_TEST_CLOSED_PLOTS``
is set (conftest sets it for a test not marked ``plots``) when a child starts and when it saves a figure, the child's
``distilkit.report.plots.save`` closes the figure and writes an empty file, as conftest's stand-in does in the test's
own process (read again at each call: a child that is itself a test run, the GPU check's, sets it per test). A finder on
``sys.meta_path`` wraps the module when it is imported: a child imports nothing it did not import before but this
file and, with the plots module, _closed_plots.py beside it (neither imports more than Python has loaded)."""

import os
import sys


class _ClosedPlots:
    """Finds ``distilkit.report.plots`` with the other finders and wraps its ``save`` once it has run."""

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name != "distilkit.report.plots":
            return None
        for finder in sys.meta_path:
            if finder is cls or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None and spec.loader is not None:
                run = spec.loader.exec_module

                def exec_module(module, run=run):
                    run(module)
                    from _closed_plots import closing

                    module.save = closing(module.save, lambda: not os.environ.get("DISTILKIT_TEST_CLOSED_PLOTS"))

                spec.loader.exec_module = exec_module
                return spec
        return None


if os.environ.get("DISTILKIT_TEST_CLOSED_PLOTS"):  # started by a test that does not look (not pytest's workers)
    sys.meta_path.insert(0, _ClosedPlots)
