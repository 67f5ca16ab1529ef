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

from distilkit.losses.ce import weighted_cross_entropy


def _check_logits_labels(logits: Tensor, labels: Tensor, fn: str) -> None:
    if logits.dim() < 2 or labels.shape != logits.shape[:1] + logits.shape[2:]:
        raise ValueError(
            f"{fn}: logits (B, K, *S) and labels (B, *S) must agree, got logits {tuple(logits.shape)} "
            f"and labels {tuple(labels.shape)}"
        )


def cross_entropy(logits: Tensor, labels: Tensor, ignore_index: int = 255, weight: Tensor | None = None) -> Tensor:
    """Mean CE over labelled positions. logits ``(B,K,*S)``, labels ``(B,*S)`` long; 0 if nothing is labelled.

    ``F.cross_entropy``'s value, reduced deterministically on CUDA (:func:`~distilkit.losses.weighted_cross_entropy`:
    PyTorch flags its 'mean' over ``(B, K, *S)`` logits, ``nll_loss2d_forward_out_cuda_template``)."""
    _check_logits_labels(logits, labels, "cross_entropy")
    valid = labels != ignore_index
    if not bool(valid.any()):
        return logits.sum() * 0.0
    return weighted_cross_entropy(logits, labels.long(), weight, ignore_index)


def lovasz_softmax(logits: Tensor, labels: Tensor, ignore_index: int = 255, classes: str = "present") -> Tensor:
    """Lovász-softmax on softmax(logits) over the flattened batch.

    Args:
        logits: ``(B, K, *S)`` raw scores (softmax is applied here, over dim 1).
        labels: ``(B, *S)`` class ids, ``ignore_index`` dropped.
        classes: ``"present"`` averages over classes that occur in the labels; ``"all"`` over all K.

    All classes are handled at once: one column-wise sort of the (P, K) error matrix.

    The counts in the Jaccard index (labelled voxels, and their running number in the sorted order) are summed in
    integers, not with a floating-point ``cumsum``: PyTorch flags ``cumsum`` of floating-point CUDA tensors
    (``cumsum_cuda_kernel does not have a deterministic implementation``) from 1.13 (pytorch#75693) to 2.5; a
    deterministic scan came with pytorch#140887 (Nov 2024, torch 2.6), while ``torch.use_deterministic_algorithms``'
    docstring still lists ``torch.cumsum`` among the ops that raise (torch 2.13). Integer sums are exact and never
    flagged, so this holds for every torch >= 2.4 that distilkit supports; the counts are whole numbers either way, so
    the value is bitwise the earlier floating-point one wherever that was exact (fewer than 2^24 labelled voxels in
    float32), and exact beyond.
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
    hits = F.one_hot(flat, k).bool()  # (P, K)
    errors = (hits.to(probs.dtype) - probs).abs()
    errors_sorted, perm = torch.sort(errors, dim=0, descending=True)
    # the counts of the Jaccard index in integers: exact, and no floating-point cumsum (flagged on CUDA, see above)
    seen = hits.gather(0, perm).cumsum(0, dtype=torch.int32)  # labelled c among the first i+1 sorted
    gts = seen[-1]
    rank = torch.arange(1, seen.shape[0] + 1, device=seen.device, dtype=torch.int32)[:, None]
    inter = (gts - seen).to(probs.dtype)
    union = (gts + rank - seen).to(probs.dtype)  # gts + (not c among the first i+1)
    jaccard = 1.0 - inter / union
    jaccard = torch.cat([jaccard[:1], jaccard[1:] - jaccard[:-1]], dim=0)
    per_class = (errors_sorted * jaccard.detach()).sum(0)
    if classes == "present":
        present = gts > 0
        return per_class[present].mean()
    return per_class.mean()
