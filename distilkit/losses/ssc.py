"""The supervised losses of camera SSC (MonoScene, VoxFormer, Scribble2Scene) as plain functions on voxel logits.

``logits`` are (B, K, X, Y, Z) (or any (B, K, ...)), ``target`` (B, X, Y, Z) int labels with ``ignore_index`` for voxels
that carry none. seed_code.md §5 gives the authors' exact definitions; where they divide by zero (an empty ground truth
in ``geo_scal``, no valid voxel at all), the term that would be 0/0 is left out here, so the losses stay finite.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.data.classes import IGNORE_INDEX
from distilkit.losses.ce import weighted_cross_entropy


def _bce_one(x: Tensor) -> Tensor:
    """``F.binary_cross_entropy(x, 1)`` = -log x, with PyTorch's clamp of the log at -100."""
    return -torch.log(x).clamp_min(-100.0)


def weighted_ce(logits: Tensor, target: Tensor, weight: Tensor | None = None,
                normalize: Literal["valid", "weight"] = "valid", ignore_index: int = IGNORE_INDEX) -> Tensor:
    """Class-weighted voxel cross entropy: Σ_v w_{y_v} ℓ_v over the valid voxels, divided by their number
    (``normalize="valid"``, VoxelFormer's ``reduction='none'`` then the mean over valid voxels) or by Σ_v w_{y_v}
    (``"weight"``, MonoScene's ``reduction='mean'``). 0 (with a gradient) where no voxel is valid."""
    per_voxel = weighted_cross_entropy(logits, target.long(), weight, ignore_index, reduction="none")
    valid = target != ignore_index
    if normalize == "valid":
        return per_voxel.sum() / valid.sum().clamp_min(1)
    if normalize != "weight":
        raise ValueError(f"normalize must be 'valid' or 'weight', got {normalize!r}")
    w = weight[target.long().clamp(0, logits.shape[1] - 1)] if weight is not None else torch.ones_like(per_voxel)
    total = (w * valid).sum()
    return per_voxel.sum() / total if bool(total > 0) else per_voxel.sum() * 0.0


def partial_ce(logits: Tensor, scribble: Tensor, weight: Tensor | None = None, ignore_index: int = IGNORE_INDEX,
               unlabelled: int = 254, empty_index: int = 0) -> Tensor:
    """Scribble2Scene's partial cross entropy (Dean-Labeler): the mean CE over the voxels a scribble labels with a
    class — neither ``empty_index``, nor ``unlabelled``, nor ``ignore_index`` — every other voxel left out."""
    labelled = (scribble != ignore_index) & (scribble != unlabelled) & (scribble != empty_index)
    target = torch.where(labelled, scribble.long(), torch.full_like(scribble.long(), ignore_index))
    return weighted_ce(logits, target, weight, "valid", ignore_index)


def geo_scal(logits: Tensor, target: Tensor, ignore_index: int = IGNORE_INDEX, empty_index: int = 0) -> Tensor:
    """MonoScene's scene-class affinity loss on geometry: with q = 1 - softmax(logits)[empty] over the valid voxels,
    -log(precision) - log(recall) - log(specificity) of q against the non-empty ground truth, where precision =
    Σ q·[y ≠ empty] / Σ q, recall = Σ q·[y ≠ empty] / Σ [y ≠ empty], specificity = Σ (1-q)·[y = empty] / Σ [y = empty].
    A term whose denominator is 0 is left out; with no occupied voxel in the ground truth, precision (then 0 whatever
    is predicted: MonoScene adds a constant 100) and recall (0/0: NaN in MonoScene) are left out, specificity stays."""
    p_empty = F.softmax(logits, dim=1).select(1, empty_index)
    valid = target != ignore_index
    q = (1.0 - p_empty)[valid]
    occupied = (target[valid] != empty_index).to(q.dtype)
    inter = (q * occupied).sum()
    loss = logits.sum() * 0.0
    if bool(occupied.sum() > 0):  # else precision is 0 whatever is predicted (a constant 100) and recall 0/0
        loss = loss + _bce_one(inter / q.sum()) + _bce_one(inter / occupied.sum())
    if bool((1 - occupied).sum() > 0):
        loss = loss + _bce_one(((1 - q) * (1 - occupied)).sum() / (1 - occupied).sum())
    return loss


def sem_scal(logits: Tensor, target: Tensor, ignore_index: int = IGNORE_INDEX) -> Tensor:
    """MonoScene's scene-class affinity loss on semantics: for every class c (empty included) present among the valid
    voxels, with p_c = softmax(logits)_c and t_c = [y = c] over them, -log P_c - log R_c - log S_c where
    P_c = Σ p_c t_c / Σ p_c (when Σ p_c > 0), R_c = Σ p_c t_c / Σ t_c, S_c = Σ (1-p_c)(1-t_c) / Σ (1-t_c) (when some
    voxel is not c); the mean over the present classes. Computed for all classes at once: O(K·N), no loop over K."""
    k = logits.shape[1]
    valid = target != ignore_index
    p = F.softmax(logits, dim=1).movedim(1, -1)[valid]  # (N, K)
    y = target[valid].long()
    n = p.shape[0]
    if n == 0:
        return logits.sum() * 0.0
    counts = torch.bincount(y, minlength=k)[:k].to(p.dtype)  # Σ t_c
    inter = torch.zeros(k, dtype=p.dtype, device=p.device).index_add(0, y, p.gather(1, y[:, None])[:, 0])  # Σ p_c t_c
    mass = p.sum(0)  # Σ p_c
    present = counts > 0
    rest = n - counts  # Σ (1 - t_c)
    one = torch.ones_like(mass)

    def term(numerator: Tensor, denominator: Tensor, used: Tensor) -> Tensor:  # -log(num/den) where used, else 0
        ratio = torch.where(used, numerator / torch.where(used, denominator, one), one)
        return _bce_one(ratio.clamp_min(0.0))

    precision = term(inter, mass, present & (mass > 0))
    recall = term(inter, counts, present)
    specificity = term(rest - mass + inter, rest, present & (rest > 0))  # Σ (1-p_c)(1-t_c) = N - Σp_c - Σt_c + Σp_c t_c
    return (precision + recall + specificity).sum() / present.sum()


def log_frequency_weights(counts: Tensor, scale: float = 10.0) -> Tensor:
    """Class weights ``scale / ln(f_c + 0.001)`` from class counts f_c: VoxFormer's (scale 10; its table of SemanticKITTI
    weights is this formula on MonoScene's frequencies) and MonoScene's (scale 1)."""
    return (scale / torch.log(counts.double() + 0.001)).float()


# HASSC's and VoxFormer's class weights for SemanticKITTI's 20 classes (release hassc_voxformer_head.py): 10 / ln(f_c +
# 0.001) on SemanticKITTI's voxel counts, rounded to 3 digits
RELEASE_WEIGHTS_SEMANTICKITTI = (0.446, 0.603, 0.852, 0.856, 0.747, 0.734, 0.801, 0.796, 0.818, 0.557, 0.653, 0.568,
                                 0.683, 0.560, 0.603, 0.530, 0.688, 0.574, 0.716, 0.786)


def split_class_weights(train_set: object, num_classes: int, field: str = "voxel_label",
                        scale: float = 10.0) -> Tensor:
    """``scale / ln(f_c + 0.001)`` from the training split's counts of ``field`` (a class never seen gets the largest
    weight; all ones when no class is seen)."""
    from distilkit.data.stats import label_counts

    voxel, _ = label_counts(train_set, num_classes, field)
    present = voxel > 0
    w = log_frequency_weights(voxel.clamp_min(1), scale)
    return w.masked_fill(~present, float(w[present].max()) if bool(present.any()) else 1.0)


def class_weights(kind: str, train_set: object, num_classes: int, field: str = "voxel_label",
                  scale: float = 10.0) -> Tensor:
    """A term's class weights by name: ``log_frequency`` (:func:`split_class_weights`), ``release`` (the releases'
    SemanticKITTI table: the data must have its 20 classes) or ``none`` (ones)."""
    if kind == "none":
        return torch.ones(num_classes)
    if kind == "release":
        if num_classes != len(RELEASE_WEIGHTS_SEMANTICKITTI):
            raise ValueError(f"class_weights: release is the table of SemanticKITTI's 20 classes; the data has "
                             f"{num_classes} (use log_frequency)")
        return torch.tensor(RELEASE_WEIGHTS_SEMANTICKITTI)
    if kind == "log_frequency":
        return split_class_weights(train_set, num_classes, field, scale)
    raise ValueError(f"unknown class weights {kind!r} (log_frequency, release or none)")


__all__ = ["RELEASE_WEIGHTS_SEMANTICKITTI", "class_weights", "split_class_weights", "geo_scal", "log_frequency_weights", "partial_ce", "sem_scal", "weighted_ce"]
