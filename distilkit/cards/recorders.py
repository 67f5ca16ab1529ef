"""The recorders' declarations (torch-free): MMRazor's recorder kinds a recipe's ``taps: {..., at: ...}`` names;
the hooks that record (:mod:`distilkit.engine.assemble.recorders`) are imported when a model is built."""

from __future__ import annotations

from distilkit.registry import RECORDERS

_IMPL = "distilkit.engine.assemble.recorders"

RECORDERS.declare("output", f"{_IMPL}:_output", card=None, description="the submodule's output (a forward hook)",
                  paper="MMRazor's ModuleOutputs")
RECORDERS.declare("input", f"{_IMPL}:_input", card=None, description="the submodule's first input (a forward hook)",
                  paper="MMRazor's ModuleInputs")
RECORDERS.declare("method", f"{_IMPL}:_method", card=None,
                  description="the return value of a method of the submodule (`method:`)",
                  paper="MMRazor's MethodOutputs")
