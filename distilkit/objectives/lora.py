"""Low-rank adapters (Hu et al., ICLR 2022) for an auxiliary copy of a frozen network (ScoreLiDAR §4.1:
"a low-rank adapter of the teacher model"). Written here: ``peft`` needs ``transformers``."""

from __future__ import annotations

import copy

import torch
from torch import Tensor, nn


class LoRALinear(nn.Module):
    """y = base(x) + (alpha / r) x A^T B^T with ``base`` frozen, A (r, in) small random, B (out, r) zero: the
    adapted layer starts as the base layer."""

    def __init__(self, base: nn.Linear, rank: int, alpha: float | None = None) -> None:
        super().__init__()
        self.base = base
        for p in self.base.parameters():
            p.requires_grad_(False)
        self.scale = (alpha if alpha is not None else rank) / rank
        self.lora_a = nn.Parameter(torch.randn(rank, base.in_features) / base.in_features ** 0.5)
        self.lora_b = nn.Parameter(torch.zeros(base.out_features, rank))

    def forward(self, x: Tensor) -> Tensor:
        return self.base(x) + self.scale * (x @ self.lora_a.T) @ self.lora_b.T


def lora_copy(module: nn.Module, rank: int) -> nn.Module:
    """A deep copy of ``module`` whose every ``nn.Linear`` is a :class:`LoRALinear` of rank ``rank``; only the
    low-rank factors are trainable."""
    out = copy.deepcopy(module)
    for p in out.parameters():
        p.requires_grad_(False)
    for name, child in list(out.named_modules()):
        for attr, sub in list(child.named_children()):
            if isinstance(sub, nn.Linear):
                setattr(child, attr, LoRALinear(sub, min(rank, sub.in_features, sub.out_features)))
    return out


def full_copy(module: nn.Module) -> nn.Module:
    """A trainable deep copy (what ScoreLiDAR's released code uses for its auxiliary network)."""
    out = copy.deepcopy(module)
    for p in out.parameters():
        p.requires_grad_(True)
    return out


__all__ = ["LoRALinear", "full_copy", "lora_copy"]
