"""Distillation objectives as plain differentiable functions: tensors in, scalar tensor out.

>>> import torch, distilkit.losses as L
>>> L.dskd(torch.randn(100, 32), torch.randn(100, 32))   # SCPNet eq. 1-2
"""

from distilkit.losses.dskd import dskd
from distilkit.losses.segmentation import cross_entropy, lovasz_softmax

__all__ = ["dskd", "cross_entropy", "lovasz_softmax"]
