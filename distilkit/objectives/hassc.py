"""HASSC's self-distillation KD as an objective (Wang et al., CVPR 2024; release songw-zju/HASSC,
``utils/ssc_loss.py``): per-voxel KL over the valid voxels, times exp(the teacher's batch mIoU)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.hassc import hassc_kd, teacher_batch_miou
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.common import release_labels


class HASSCKDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    dynamic_weight: bool = Field(True, description="times exp(mIoU of the teacher's argmax on the batch), the "
                                                   "release's weight; false: the KL term alone")


class HASSCKD(MultiTapObjective):
    """HASSC's KD: T^2 KL(p_T || p_S) per valid voxel, the mean per sample, then over the batch, times exp(the
    teacher's mIoU on the batch) (the release's dynamic weight, absent classes counted as 0); weight 48 as the
    release. HASSC's teacher is the student's own EMA; any teacher edge serves."""

    CHOICES = (Choice("the batch reduction", "the mean over samples", "not stated", "the sum of per-sample means "
                      "(the same at its batch size of 1)"),
               Choice("the dynamic weight's mIoU", "classes absent from the batch count as IoU 0, as the release",
                      "the teacher's mIoU", "computed over all classes, absent ones 0", "`dynamic_weight: false`"))
    Params = HASSCKDParams
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 48.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        teacher = taps["teacher"].detach()
        miou = teacher_batch_miou(teacher, labels) if self.params.dynamic_weight else None
        return hassc_kd(taps["student"], teacher, labels, self.params.temperature, miou)


register_objective("hassc_kd", HASSCKD, description="HASSC's KD: per-voxel KL over valid voxels × exp(teacher "
                   "mIoU)", paper="HASSC (Wang et al., CVPR 2024), utils/ssc_loss.py",
                   equation="exp(mIoU_T) · mean_b mean_{v valid} T² KL(softmax(t_v/T) ‖ softmax(s_v/T))",
                   shapes="(B, K, X, Y, Z) logits, student and teacher")
