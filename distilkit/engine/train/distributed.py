"""Multi-process training: the processes of one run (``distilkit run --nproc-per-node N``, launched by PyTorch's
elastic launcher ``torchrun``) and what they share.

Each process trains the same student on its share of every global batch (``train.batch_size`` is the global
batch: sample ``j`` of a batch goes to rank ``j mod N``); after the backward pass the gradients of everything
the stage optimizes — student, connectors, the networks objectives own (FitNets' regressor, MGD's generator) —
are averaged over the processes in one flattened all-reduce, so every process takes the same step, the way DDP
averages a model's gradients. Terms that train their own network (VSD's score network) average theirs through
:attr:`distilkit.term.TermContext.sync`. The frozen teacher is not synchronised (it does not train). Only rank 0
writes (checkpoints, logs, summaries, reports); each process evaluates its share of a split and the metrics' states are
merged (:mod:`distilkit.engine.train.evaluate`), so every scene is scored once.

Equal to one process on the same global batch when the loss of a batch is the mean of per-sample losses of
equal weight and the model has no batch statistics. BatchNorm layers use each process's own share (as DDP
without SyncBatchNorm does; PyTorch's SyncBatchNorm runs on GPUs only, and is switched on there).
"""

from __future__ import annotations

import datetime
import os
import sys
from dataclasses import dataclass
from typing import Iterable, Mapping

import torch
from torch import nn


@dataclass(frozen=True)
class World:
    """The processes of a run: this one's ``rank`` among ``size`` (1: no distribution)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        """The process that writes."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    def shard(self, indices: list[int]) -> list[int]:
        """This process's samples of a global batch."""
        return indices[self.rank::self.size]

    def average_gradients(self, params: Iterable[nn.Parameter]) -> None:
        """Replace each parameter's gradient by its mean over the processes (a missing gradient counts as 0)."""
        if not self.distributed:
            return
        params = [p for p in params if p.requires_grad]
        if not params:
            return
        flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in params])
        torch.distributed.all_reduce(flat)
        flat /= self.size
        offset = 0
        for p in params:
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p).clone()
            offset += n

    def any(self, flag: bool) -> bool:
        """Whether ``flag`` is true in any process (so that all stop together, none waits for the others)."""
        if not self.distributed:
            return flag
        t = torch.tensor([1.0 if flag else 0.0])
        torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
        return bool(t.item() > 0)

    def barrier(self) -> None:
        if self.distributed:
            torch.distributed.barrier()

    def finish(self) -> None:
        """Wait for the others at the end of a run, so that every process exits together: a gloo process whose peer
        has exited mid-connection can abort at exit ("terminate called without an active exception"; seen here in
        1 of 6 runs without this barrier, and with it followed by destroy_process_group, none in 18 with it alone)."""
        if self.distributed and torch.distributed.is_initialized():
            torch.distributed.barrier()


SINGLE = World()


def leave(world: World, code: int = 0) -> None:
    """End this process of a multi-process run once every process is done: wait for the others, flush the output and
    exit without the interpreter's teardown. Gloo's process group can abort in its destructor at exit even after a
    barrier ("terminate called without an active exception", SIGABRT; 1 in about 10 CI runs of the two-process
    tests), which turned finished runs into failed ones. A single process returns and exits normally."""
    if not (world.distributed and torch.distributed.is_initialized()):
        return
    world.finish()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def first_host(nodelist: str) -> str:
    """The first host of a Slurm node list (``node[03-05,07],gpu1`` -> ``node03``): ``scontrol show hostnames`` where
    it answers, else read off the list."""
    import shutil
    import subprocess

    if shutil.which("scontrol"):
        done = subprocess.run(["scontrol", "show", "hostnames", nodelist], capture_output=True, text=True)
        if done.returncode == 0 and done.stdout.strip():
            return done.stdout.split()[0]
    head = nodelist.split(",")[0] if "[" not in nodelist.split(",")[0] else nodelist
    if "[" not in head:
        return head
    prefix, rest = head.split("[", 1)
    return prefix + rest.split("]")[0].split(",")[0].split("-")[0]


def from_slurm() -> None:
    """Inside a Slurm step of several tasks (``srun``: ``SLURM_STEP_ID`` set, ``SLURM_NTASKS`` > 1) and not under
    torchrun: the variables torchrun would set, from Slurm's — ``RANK`` = ``SLURM_PROCID``, ``WORLD_SIZE`` =
    ``SLURM_NTASKS``, ``LOCAL_RANK`` = ``SLURM_LOCALID``, ``MASTER_ADDR`` the step's first node, ``MASTER_PORT`` from
    the job id — so that ``srun distilkit run ...`` trains with one process per task. A batch script (no step) is one
    process whatever ``--ntasks`` says."""
    env = os.environ
    if "WORLD_SIZE" in env or "SLURM_STEP_ID" not in env or int(env.get("SLURM_NTASKS", "1")) <= 1:
        return
    env["RANK"], env["WORLD_SIZE"] = env["SLURM_PROCID"], env["SLURM_NTASKS"]
    env["LOCAL_RANK"] = env.get("SLURM_LOCALID", "0")
    env.setdefault("MASTER_ADDR", first_host(env.get("SLURM_STEP_NODELIST") or env.get("SLURM_JOB_NODELIST",
                                                                                       "localhost")))
    env.setdefault("MASTER_PORT", str(20000 + int(env.get("SLURM_JOB_ID", "0")) % 20000))


AUTO = "*"  # the stages of a run whose devices world_from_env was not given: as ``auto`` would pick


def cuda_stages(devices: Mapping[str, torch.device] | None) -> list[str]:
    """The stages of ``devices`` (stage name -> the device it trains on) that train on CUDA."""
    return [name for name, device in (devices or {}).items() if torch.device(device).type == "cuda"]


def refuse_more_processes_than_gpus(processes: int, devices: Mapping[str, torch.device], how: str) -> None:
    """A :class:`~distilkit.errors.DistilkitError` when ``processes`` processes on this node (``how``: who starts
    them, e.g. ``--nproc-per-node 2``) would train stages on CUDA and the node has fewer GPUs
    (``torch.cuda.device_count()``): each process of a run trains on a GPU of its own
    (``torch.cuda.set_device(LOCAL_RANK)``; NCCL refuses two ranks on one GPU). Stages that all train on the CPU need
    no GPU: nothing is refused."""
    on_cuda = cuda_stages(devices)
    if not on_cuda or processes <= 1:
        return
    count = torch.cuda.device_count()
    if processes <= count:
        return
    from distilkit.errors import DistilkitError

    stages = (f"the stages (train.device auto, a GPU available) train" if on_cuda == [AUTO] else
              f"stages {', '.join(on_cuda)} train" if len(on_cuda) > 1 else f"stage {on_cuda[0]} trains")
    fewer = f"start at most {count} per node, or " if count else ""
    raise DistilkitError(f"{processes} processes on this node ({how}) and {stages} on cuda, one GPU per process: this "
                         f"node has {count} GPU{'' if count == 1 else 's'} (torch.cuda.device_count()); {fewer}train "
                         "on the CPU with --set 'stages.*.train.device=cpu' (gloo over the host)")


def _node_processes(local: int) -> tuple[int, str]:
    """How many processes of the run this node holds, at least, and who said so: torchrun's ``LOCAL_WORLD_SIZE``
    (``--nproc-per-node``), Slurm's tasks per node (the most on any node of the step: a run one node cannot hold
    stops everywhere), else ``LOCAL_RANK + 1``."""
    env = os.environ
    if "LOCAL_WORLD_SIZE" in env:
        return int(env["LOCAL_WORLD_SIZE"]), (f"torchrun's --nproc-per-node {env['LOCAL_WORLD_SIZE']}; this one "
                                             f"LOCAL_RANK {local}")
    import re

    for key in ("SLURM_STEP_TASKS_PER_NODE", "SLURM_TASKS_PER_NODE", "SLURM_NTASKS_PER_NODE"):
        counts = [int(n) for n in re.findall(r"(\d+)(?:\(x\d+\))?", env.get(key, ""))]
        if counts and "SLURM_LOCALID" in env:
            return max(max(counts), local + 1), f"Slurm's {key}={env[key]}; this one SLURM_LOCALID {local}"
    if "SLURM_LOCALID" in env and "TORCHELASTIC_RUN_ID" not in env:
        return local + 1, f"Slurm's SLURM_LOCALID {local}"
    return local + 1, f"LOCAL_RANK {local}"


def world_from_env(devices: Mapping[str, torch.device] | None = None) -> World:
    """The world ``torchrun`` describes in the environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``; or Slurm's
    tasks of an ``srun`` step, :func:`from_slurm`), its process group started; a single process without them.

    ``devices``: the device each stage of the run trains on (stage name -> device,
    :func:`~distilkit.engine.assemble.devices.stage_devices`). Where a stage trains on CUDA, each process takes the GPU
    of its ``LOCAL_RANK`` (``torch.cuda.set_device``) and CUDA tensors are reduced by NCCL (CPU ones by gloo); more
    processes on the node than GPUs is then an error naming both (:func:`refuse_more_processes_than_gpus`; ``distilkit
    run --nproc-per-node N`` refuses it before starting torchrun, this in each process for torchrun or Slurm started
    directly) — two processes are not put on one GPU. Where every stage trains on the CPU, the processes need the
    host only: gloo, no ``set_device``, whatever GPUs the machine has (so two processes on a one-GPU machine run
    there). ``None`` (the stages are not known: the library's own callers pass them): CUDA where a GPU is available,
    as a stage on ``auto`` would train. The first call of a process starts the group; later ones read it."""
    from_slurm()
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return SINGLE
    rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    if not torch.distributed.is_initialized():
        if devices is None:
            devices = {AUTO: torch.device("cuda" if torch.cuda.is_available() else "cpu")}
        backend = "gloo"
        if cuda_stages(devices):
            processes, how = _node_processes(local)
            refuse_more_processes_than_gpus(processes, devices, how)
            torch.cuda.set_device(local)
            backend = "cpu:gloo,cuda:nccl"
        torch.distributed.init_process_group(backend, timeout=datetime.timedelta(hours=2))
    return World(rank, size, local)


def sync_batchnorm(model: nn.Module, world: World, device: torch.device) -> nn.Module:
    """BatchNorm statistics over all processes where PyTorch supports it (CUDA); unchanged otherwise."""
    if world.distributed and device.type == "cuda":
        return nn.SyncBatchNorm.convert_sync_batchnorm(model)
    return model


__all__ = ["SINGLE", "World", "cuda_stages", "first_host", "from_slurm", "leave", "refuse_more_processes_than_gpus",
           "sync_batchnorm", "world_from_env"]
