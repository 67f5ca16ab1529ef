"""``distilkit run ... --nproc-per-node N``: the same command in N processes per node, started by PyTorch's elastic
launcher (torchrun), each with its share of the CPU's threads."""

from __future__ import annotations

import os
import subprocess
import sys

from distilkit.errors import DistilkitError


def launch(run_args: list[str], nproc: int, nnodes: int = 1, node_rank: int = 0, master_addr: str = "127.0.0.1",
           master_port: int = 29500) -> int:
    """Run ``distilkit run RUN_ARGS`` in ``nproc`` processes on this node (one of ``nnodes``); its exit status."""
    if nproc < 1 or nnodes < 1:
        raise DistilkitError(f"--nproc-per-node and --nnodes must be at least 1, got {nproc} and {nnodes}")
    where = (["--standalone"] if nnodes == 1 else
             [f"--nnodes={nnodes}", f"--node-rank={node_rank}", f"--master-addr={master_addr}",
              f"--master-port={master_port}"])
    from distilkit.engine.train.cpus import usable_cpus

    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", str(max(1, usable_cpus() // nproc)))}
    cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc-per-node={nproc}", *where, "-m", "distilkit",
           "run", *run_args]
    return subprocess.call(cmd, env=env)


__all__ = ["launch"]
