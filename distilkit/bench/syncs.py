"""Counting the points where the host waits for the device's values (``.item()``, ``bool()``, ``.tolist()``,
``nonzero``, boolean-mask indexing, ``unique``, ``repeat_interleave`` without its size): on CUDA with PyTorch's own
sync debug mode (a warning per synchronising call), on the CPU — where nothing waits — by the ops that would, seen
by a ``TorchDispatchMode``. ``distilkit bench step`` counts a training step's; tests/test_sparse_syncs.py the sparse
path's. Not a benchmark: no case is registered here."""

from __future__ import annotations

import contextlib
import warnings
from typing import Any, Iterator

import torch
from torch.utils._python_dispatch import TorchDispatchMode

SYNCING = {"aten._local_scalar_dense.default", "aten.nonzero.default", "aten.masked_select.default",
           "aten._unique2.default", "aten.unique_dim.default", "aten.unique_consecutive.default"}


class _Counter(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.ops: list[str] = []

    def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
        name = str(func)
        kwargs = kwargs or {}
        if name in SYNCING:
            self.ops.append(name)
        elif name == "aten.index.Tensor" and any(i is not None and i.dtype == torch.bool for i in args[1]):
            self.ops.append("boolean mask")
        elif name.startswith("aten.repeat_interleave") and kwargs.get("output_size") is None and \
                len(args) < 3 and isinstance(args[0], torch.Tensor) and args[0].dtype != torch.bool:
            self.ops.append(name)
        return func(*args, **kwargs)


@contextlib.contextmanager
def host_syncs(device: torch.device) -> Iterator[list[str]]:
    """The list of host syncs made inside the block on ``device`` (filled when the block ends): on CUDA the first
    line of each warning of ``torch.cuda.set_sync_debug_mode("warn")``, elsewhere the name of each op that would
    sync there (``tolist`` counted by name)."""
    found: list[str] = []
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                yield found
                torch.cuda.set_sync_debug_mode("default")
            found += [str(w.message).splitlines()[0] for w in caught if "synchroniz" in str(w.message)]
        finally:
            torch.cuda.set_sync_debug_mode("default")
        return
    tolist = torch.Tensor.tolist

    def counted(self: torch.Tensor) -> Any:
        found.append("tolist")
        return tolist(self)

    torch.Tensor.tolist = counted  # type: ignore[method-assign]
    try:
        with _Counter() as counter:
            yield found
        found += counter.ops
    finally:
        torch.Tensor.tolist = tolist  # type: ignore[method-assign]


__all__ = ["SYNCING", "host_syncs"]
