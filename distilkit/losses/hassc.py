"""HASSC's self-distillation term (Wang et al., CVPR 2024, "Not All Voxels Are Equal"; release songw-zju/HASSC,
``utils/ssc_loss.py``), as the release computes it.

:func:`hassc_kd`: per valid voxel (label != 255) KL(softmax(z_T / T) || softmax(z_S / T)) T^2 summed over the
classes, averaged over the sample's valid voxels, then over the samples (the release sums the per-sample means; at
its batch size of 1 the two agree; a sample without a valid voxel gives 0), times exp(mIoU) of the teacher's argmax
on this batch when given — the release's dynamic weight (:func:`teacher_batch_miou`: its mIoU counts a class absent
from the batch, neither predicted nor labelled, as IoU 0).
"""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.losses.logit import kl_per_sample


def hassc_kd(student_logits: Tensor, teacher_logits: Tensor, labels: Tensor, temperature: float = 1.0,
             teacher_miou: float | Tensor | None = None) -> Tensor:
    """HASSC's KD term on (B, K, *spatial) logits and (B, *spatial) labels (255 ignored): see the module docstring."""
    if student_logits.shape != teacher_logits.shape or labels.shape != student_logits.shape[:1] + \
            student_logits.shape[2:]:
        raise ValueError(f"hassc_kd: student {tuple(student_logits.shape)}, teacher {tuple(teacher_logits.shape)} and "
                         f"labels {tuple(labels.shape)} must be (B, K, *spatial) twice and (B, *spatial)")
    if temperature <= 0:
        raise ValueError(f"hassc_kd: temperature must be positive, got {temperature}")
    t = float(temperature)
    loss = kl_per_sample(student_logits, teacher_logits, labels != 255, t).mean() * t * t
    if teacher_miou is not None:
        loss = loss * torch.exp(torch.as_tensor(teacher_miou, dtype=loss.dtype, device=loss.device))
    return loss


def teacher_batch_miou(teacher_logits: Tensor, labels: Tensor, ignore_index: int = 255) -> Tensor:
    """The mIoU of the teacher's argmax against ``labels`` over the batch's voxels that are not ignored, averaged over
    all K classes with a class absent from both as IoU 0 (HASSC's dynamic weight); no gradient."""
    with torch.no_grad():
        k = teacher_logits.shape[1]
        pred = teacher_logits.argmax(1).reshape(-1)
        gt = labels.reshape(-1)
        keep = gt != ignore_index
        pred, gt = pred[keep], gt[keep].long()
        inter = torch.bincount(gt[pred == gt], minlength=k)[:k].double()
        union = (torch.bincount(pred, minlength=k)[:k] + torch.bincount(gt, minlength=k)[:k]).double() - inter
        iou = torch.where(union > 0, inter / union.clamp_min(1), torch.zeros_like(union))
        return iou.mean().to(teacher_logits.dtype)


__all__ = ["hassc_kd", "teacher_batch_miou"]
