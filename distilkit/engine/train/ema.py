"""A stage's own teacher: the exponential moving average of its student (HASSC's mean teacher,
``teacher: {ema: ...}``).

HASSC (Wang et al., CVPR 2024, §3.4; release ``detectors/hassc_voxformer.py``): the teacher is a copy of the student
at step 0 and, before the forward of every step k = 0, 1, ... (so after optimiser step k − 1),
``t ← m·t + (1 − m)·s`` with ``m = min(1 − 1/(k + 1), 0.99)``, under ``no_grad``. Two choices, both offered
(:class:`~distilkit.recipe.schema.EmaSpec`):

* **buffers** — the release averages ``parameters()`` only; the buffers (BatchNorm statistics) are those of the
  student's full state dict loaded at step 0. Default here ``average``: floating-point buffers are averaged like
  the parameters (integer ones, e.g. ``num_batches_tracked``, copied), so an eval-mode teacher normalises with
  statistics of the weights it has; ``copy_once`` is the release's.
* **mode** — the release calls ``teacher.eval()`` once, but mmcv's runner calls ``model.train()`` on the detector
  every epoch and the teacher is its submodule, so the released teacher runs in train mode (its hard-voxel head
  even needs it: ``sampled_voxel_coords`` exists only in training). Default here ``eval`` (the paper's, and what
  the release asks for); ``train`` is the release's behaviour.

Its state (the averaged weights) is part of ``last.pt``, so a resumed run continues with the same bits.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from distilkit.engine.assemble.runs import build_model


class EmaTeacher:
    """The moving average of ``student`` (built like it from the resolved ``model``; draws no random numbers from the
    caller's stream), frozen: no gradients, in the spec's mode."""

    def __init__(self, model: Any, info: Any, student: nn.Module, spec: Any, device: torch.device) -> None:
        self.spec = spec
        with torch.random.fork_rng(devices=[]):
            built = build_model(model, info, role="teacher")
        built.load_state_dict(student.state_dict())
        for p in built.parameters():
            p.requires_grad_(False)
        self.model = built.to(device).train(spec.mode == "train")
        self._pairs = self._match(student)

    def _match(self, student: nn.Module) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(teacher, student) tensors by name: the parameters, and the buffers when they are averaged too."""
        t_params, s_params = dict(self.model.named_parameters()), dict(student.named_parameters())
        if t_params.keys() != s_params.keys():
            raise RuntimeError("the EMA teacher's parameters do not match the student's: "
                               f"{sorted(t_params.keys() ^ s_params.keys())[:4]}")
        pairs = [(t_params[n], s_params[n]) for n in t_params]
        if self.spec.buffers == "average":
            t_buf, s_buf = dict(self.model.named_buffers()), dict(student.named_buffers())
            pairs += [(t_buf[n], s_buf[n]) for n in t_buf if n in s_buf]
        return pairs

    def momentum(self, step: int) -> float:
        """m = min(1 − 1/(step + 1), momentum): 0 at step 0 (a copy), then 1/2, 2/3, ... up to the cap."""
        return min(1.0 - 1.0 / (step + 1), self.spec.momentum)

    @torch.no_grad()
    def update(self, step: int) -> float:
        """Move the teacher towards the student before step ``step``'s forward; returns the momentum used."""
        m = self.momentum(step)
        for t, s in self._pairs:
            if t.is_floating_point():
                t.mul_(m).add_(s.detach().to(t.dtype), alpha=1.0 - m)
            else:  # counters: the student's
                t.copy_(s)
        return m

    def state_dict(self) -> dict[str, Any]:
        return self.model.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state)


__all__ = ["EmaTeacher"]
