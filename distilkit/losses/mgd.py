"""MGD (Yang et al., ECCV 2022; a Scribble2Scene Table 5 baseline): masked generative distillation."""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from distilkit.losses.feature import fitnet


def mgd(student: Tensor, teacher: Tensor, generator: Callable[[Tensor], Tensor], mask_ratio: float = 0.65,
        keep: Tensor | None = None) -> Tensor:
    """MGD: mean (G(F_s ⊙ M) − F_t)², M ~ Bernoulli(1 − λ) per spatial position, shared by the channels.

    Args:
        student: ``(B, C, *S)`` student features, already aligned to the teacher's channels and size.
        teacher: ``(B, C, *S)`` teacher features.
        generator: the learnable generator G (MGD: conv3-ReLU-conv3), mapping ``(B, C, *S)`` to itself.
        mask_ratio: λ, the fraction of positions masked (0.65 for dense prediction in MGD).
        keep: ``(B, 1, *S)`` the mask M (1 = kept); drawn from the global random stream when not given.
    """
    if not 0.0 <= mask_ratio < 1.0:
        raise ValueError(f"mgd: mask_ratio must be in [0, 1), got {mask_ratio}")
    if keep is None:
        keep = (torch.rand((student.shape[0], 1, *student.shape[2:]), device=student.device) >= mask_ratio)
    elif keep.shape != (student.shape[0], 1, *student.shape[2:]):
        raise ValueError(f"mgd: keep must be (B, 1, *S) = {(student.shape[0], 1, *student.shape[2:])}, "
                         f"got {tuple(keep.shape)}")
    return fitnet(generator(student * keep.to(student.dtype)), teacher)
