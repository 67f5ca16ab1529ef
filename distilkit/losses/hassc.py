"""HASSC's self-distillation term (Wang et al., CVPR 2024, "Not All Voxels Are Equal"; release songw-zju/HASSC at
20097ee, ``utils/ssc_loss.py`` and ``dense_heads/hassc_voxformer_head.py``), as the release computes it.

:func:`hassc_kd`: per valid voxel (label != 255) KL(softmax(z_T / T) || softmax(z_S / T)) T^2 summed over the
classes, averaged over the sample's valid voxels (a sample without a valid voxel gives 0), times the dynamic weight
exp(mIoU of the teacher's argmax), then averaged over the samples. The release trains one sample per GPU
(``samples_per_gpu=1``): each GPU weighs its sample's KL by its own sample's mIoU and DDP averages the gradients,
so the release's value at B > 1 is the mean over samples of exp(mIoU_b) KL_b — this module's default
(``teacher_batch_miou(..., per="sample")`` gives one mIoU per sample). Its ``distill_ssc_loss`` sums the per-sample
means (one sample: the same).

:func:`teacher_batch_miou`: the release's metric (``utils/ssc_metric_torch.py``, ``get_score_semantic_and_completion``
with the mask label != 255): IoU_c = TP_c / (TP_c + FP_c + FN_c + 1e-5) over the non-ignored voxels, so that a class
neither predicted nor labelled has IoU 0, and the mean over classes 1..K-1 (``iou[1:]``: empty left out).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from distilkit.losses.logit import kl_per_sample

RELEASE_EPS = 1e-5  # the release's TP / (TP + FP + FN + 1e-5)


def hassc_kd(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, temperature: float = 1.0,
             teacher_miou: float | Tensor | None = None) -> Tensor:
    """HASSC's KD term on ``(B, K, *spatial)`` logits and ``(B, *spatial)`` labels (255 ignored): mean_b w_b T^2
    KL_b with w_b = exp(``teacher_miou``) — a scalar (one weight for the batch) or (B,) (one per sample, the
    release) — or 1 when None. See the module docstring."""
    if student_logits.shape != teacher_logits.shape or labels.shape != student_logits.shape[:1] + \
            student_logits.shape[2:]:
        raise ValueError(f"hassc_kd: student {tuple(student_logits.shape)}, teacher {tuple(teacher_logits.shape)} and "
                         f"labels {tuple(labels.shape)} must be (B, K, *spatial) twice and (B, *spatial)")
    if temperature <= 0:
        raise ValueError(f"hassc_kd: temperature must be positive, got {temperature}")
    t = float(temperature)
    per_sample = kl_per_sample(student_logits, teacher_logits, labels != 255, t) * (t * t)
    if teacher_miou is not None:
        miou = torch.as_tensor(teacher_miou, dtype=per_sample.dtype, device=per_sample.device)
        if miou.dim() > 1 or (miou.dim() == 1 and miou.shape[0] != per_sample.shape[0]):
            raise ValueError(f"hassc_kd: teacher_miou must be a scalar or one value per sample "
                             f"({per_sample.shape[0]}), got shape {tuple(miou.shape)}")
        per_sample = per_sample * torch.exp(miou)
    return per_sample.mean()


def teacher_batch_miou(teacher_logits: Tensor, labels: Tensor, ignore_index: int = 255,
                       classes: Literal["non_empty", "all"] = "non_empty",
                       per: Literal["sample", "batch"] = "sample") -> Tensor:
    """The mIoU of the teacher's argmax against ``labels`` over the voxels that are not ignored, with the release's
    IoU TP / (TP + FP + FN + 1e-5) (a class absent from both: 0), no gradient.

    ``classes``: ``non_empty`` = the mean over classes 1..K-1 (the release's ``iou[1:]``), ``all`` = over all K.
    ``per``: ``sample`` = (B,) one mIoU per sample (the release: one sample per GPU), ``batch`` = a scalar over the
    batch's voxels pooled. float32 (float64 for float64 logits)."""
    if classes not in ("non_empty", "all") or per not in ("sample", "batch"):
        raise ValueError(f"teacher_batch_miou: classes must be non_empty or all and per sample or batch, got "
                         f"{classes!r} and {per!r}")
    if labels.shape != teacher_logits.shape[:1] + teacher_logits.shape[2:]:
        raise ValueError(f"teacher_batch_miou: logits {tuple(teacher_logits.shape)} and labels "
                         f"{tuple(labels.shape)} must be (B, K, *spatial) and (B, *spatial)")
    with torch.no_grad():
        b, k = teacher_logits.shape[:2]
        pred = teacher_logits.argmax(1).reshape(b, -1)
        gt = labels.reshape(b, -1).long()
        keep = gt != ignore_index
        rows = torch.arange(b, device=gt.device)[:, None].expand_as(gt)

        def counts(which: Tensor, mask: Tensor) -> Tensor:  # (B, K) per-sample class counts where mask holds
            index = (rows * k + which.clamp(0, k - 1))[mask]
            return torch.bincount(index, minlength=b * k)[:b * k].reshape(b, k).double()

        inter = counts(gt, keep & (pred == gt))
        union = counts(pred, keep) + counts(gt, keep) - inter
        if per == "batch":
            inter, union = inter.sum(0, keepdim=True), union.sum(0, keepdim=True)
        iou = inter / (union + RELEASE_EPS)
        if classes == "non_empty":
            iou = iou[:, 1:]
        miou = iou.mean(1)
        out = miou[0] if per == "batch" else miou
        return out.to(torch.float64 if teacher_logits.dtype == torch.float64 else torch.float32)


__all__ = ["hassc_kd", "teacher_batch_miou"]
