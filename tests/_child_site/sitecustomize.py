"""Put on the ``PYTHONPATH`` of the tests' child processes by tests/conftest.py. Where ``DISTILKIT_TEST_CLOSED_PLOTS``
is set (a test not marked ``plots``), the child's ``distilkit.report.plots.save`` closes each figure and writes an
empty file, as conftest's stand-in does in the test's own process. A finder on ``sys.meta_path`` wraps the module
when it is imported: a child imports nothing it did not import before (only this file, which imports nothing)."""

import os
import sys

if os.environ.get("DISTILKIT_TEST_CLOSED_PLOTS"):
    def _save(fig, path):
        import matplotlib.pyplot as plt

        plt.close(fig)
        path.write_bytes(b"")
        return path

    class _ClosedPlots:
        """Finds ``distilkit.report.plots`` with the other finders and replaces its ``save`` once it has run."""

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
                        module.save = _save

                    spec.loader.exec_module = exec_module
                    return spec
            return None

    sys.meta_path.insert(0, _ClosedPlots)
