"""Task losses for semantic scene completion: cross entropy and Lovász-softmax.

SCPNet eq. 4: L = L_ce + alpha * L_lovasz (+ beta * L_dskd), with CE ignoring label 255
and Lovász-softmax (Berman et al. CVPR 2018) over the classes present in the ground truth,
empty class 0 included, computed over the flattened batch (``per_image=False``), as in the
authors' code (seed_code.md §1.2).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def _check_logits_labels(logits: Tensor, labels: Tensor, fn: str) -> None:
    if logits.dim() < 2 or labels.shape != logits.shape[:1] + logits.shape[2:]:
        raise ValueError(
            f"{fn}: logits (B, K, *S) and labels (B, *S) must agree, got logits {tuple(logits.shape)} "
            f"and labels {tuple(labels.shape)}"
        )


def cross_entropy(logits: Tensor, labels: Tensor, ignore_index: int = 255, weight: Tensor | None = None) -> Tensor:
    """Mean CE over labelled positions. logits (B,K,*S), labels (B,*S) long; 0 if nothing is labelled."""
    _check_logits_labels(logits, labels, "cross_entropy")
    valid = labels != ignore_index
    if not bool(valid.any()):
        return logits.sum() * 0.0
    return F.cross_entropy(logits, labels.long(), ignore_index=ignore_index, weight=weight)


def lovasz_softmax(logits: Tensor, labels: Tensor, ignore_index: int = 255, classes: str = "present") -> Tensor:
    """Lovász-softmax on softmax(logits) over the flattened batch.

    Args:
        logits: (B, K, *S) raw scores (softmax is applied here, over dim 1).
        labels: (B, *S) class ids, ``ignore_index`` dropped.
        classes: ``"present"`` averages over classes that occur in the labels; ``"all"`` over all K.

    All classes are handled at once: one column-wise sort of the (P, K) error matrix.
    """
    _check_logits_labels(logits, labels, "lovasz_softmax")
    if classes not in ("present", "all"):
        raise ValueError(f"lovasz_softmax: classes must be 'present' or 'all', got {classes!r}")
    k = logits.shape[1]
    probs = logits.softmax(dim=1).movedim(1, -1).reshape(-1, k)
    flat = labels.reshape(-1)
    keep = flat != ignore_index
    probs, flat = probs[keep], flat[keep].long()
    if flat.numel() == 0:
        return logits.sum() * 0.0
    fg = F.one_hot(flat, k).to(probs.dtype)  # (P, K)
    errors = (fg - probs).abs()
    errors_sorted, perm = torch.sort(errors, dim=0, descending=True)
    fg_sorted = fg.gather(0, perm)
    gts = fg_sorted.sum(0)
    inter = gts - fg_sorted.cumsum(0)
    union = gts + (1.0 - fg_sorted).cumsum(0)
    jaccard = 1.0 - inter / union
    jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]], dim=0)
    per_class = (errors_sorted * jaccard.detach()).sum(0)
    if classes == "present":
        present = gts > 0
        return per_class[present].mean()
    return per_class.mean()
