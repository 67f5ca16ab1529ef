"""A frozen teacher's module mode (``teacher: {mode: eval | train}``) and what train mode asks of a run.

Either way the teacher has no gradients and its outputs are computed under ``no_grad``. **eval** (default): BatchNorm
normalises with its running statistics, dropout and drop-path are off. **train**: what the releases do — L2COcc's
teacher is put in eval mode once, and PyTorch Lightning's loop calls ``.train()`` on the LightningModule that holds
it (``core/models/detectors/CameraSegmentor.py``, ``tools/pl_model.py``: its Swin's drop-path 0.2 is on); HASSC's
teacher likewise under mmcv's runner (``detectors/hassc_voxformer.py``; ``teacher: {ema: {mode: train}}``). Then
BatchNorm normalises with each batch's statistics and, as PyTorch does under ``no_grad``, **updates its running
statistics** at every teacher forward: decided as in the releases. They are never read while the teacher stays in
train mode, but they are state, so ``last.pt`` holds them (``teacher_buffers``) and a killed run resumes with the same
bits as an uninterrupted one. Dropout draws from the run's random stream, which ``last.pt`` holds too.

The setup pass that sizes connectors on batch 0 is not a training step: it runs the teacher in eval mode, as it runs
the student, and moves no statistics. With several processes the train-mode teacher's BatchNorm layers are
synchronised where the student's are (CUDA: :func:`~distilkit.engine.train.distributed.sync_batchnorm`), so they
normalise over the global batch; on CPUs each process normalises over its share, and rank 0's statistics are saved.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator

import torch
from torch import nn

from distilkit.engine.train.distributed import World, sync_batchnorm


def apply_mode(model: nn.Module, mode: str, world: World, device: torch.device) -> nn.Module:
    """The frozen ``model`` in ``mode`` (``eval`` or ``train``), synchronised BatchNorm in train mode where the
    student's is; its parameters stay without gradients."""
    if mode == "train":
        model = sync_batchnorm(model, world, device).to(device)
    for p in model.parameters():
        p.requires_grad_(False)
    return model.train(mode == "train")


def teacher_buffers(model: nn.Module) -> dict[str, torch.Tensor]:
    """The buffers a train-mode teacher changes (BatchNorm's running statistics and counters), by name."""
    return {name: buf.detach().clone() for name, buf in model.named_buffers()}


def load_teacher_buffers(model: nn.Module, state: dict[str, Any], where: str) -> None:
    """Put back what :func:`teacher_buffers` saved; a missing or extra name is an error naming ``where``."""
    own = dict(model.named_buffers())
    if own.keys() != state.keys():
        raise ValueError(f"{where}: the teacher's saved buffers do not match its model: "
                         f"{sorted(own.keys() ^ state.keys())[:4]}")
    with torch.no_grad():
        for name, buf in own.items():
            buf.copy_(state[name])


@contextlib.contextmanager
def evaluating(model: nn.Module | None) -> Iterator[None]:
    """``model`` in eval mode inside the block, in its own mode again after it (None: nothing)."""
    if model is None:
        yield
        return
    was = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was)


__all__ = ["apply_mode", "evaluating", "load_teacher_buffers", "teacher_buffers"]
