"""Logit objectives: vanilla KD and DIST on voxel logits."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.data.batch import Batch
from distilkit.losses.logit import dist, kd
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.common import MaskName, voxel_mask


class KDParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    temperature: float = Field(1.0, gt=0)
    voxels: MaskName = Field("valid", description="voxels distilled: all, valid (observed) or occupied")


class KD(MultiTapObjective):
    """Vanilla KD (Hinton et al. 2015) per voxel: T^2 mean KL(p_t || p_s) over the chosen voxels.

    Per-voxel mean, so the weight does not depend on the grid size (SCPNet Table 4 baseline).
    """

    Params = KDParams
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}  # the labels that choose the voxels
    DEFAULT_WEIGHT = 1.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        mask = voxel_mask(taps["target"], self.params.voxels, self.ignore_index)
        return kd(taps["student"], taps["teacher"], self.params.temperature, mask)


class DISTParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    beta: float = Field(1.0, ge=0, description="inter-class (per voxel) weight")
    gamma: float = Field(1.0, ge=0, description="intra-class (per class across voxels) weight")
    temperature: float = Field(1.0, gt=0)
    voxels: MaskName = "valid"


class DIST(MultiTapObjective):
    """DIST (Huang et al., NeurIPS 2022) with voxels as the rows (Scribble2Scene Table 5 baseline)."""

    Params = DISTParams
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}  # the labels that choose the voxels
    DEFAULT_WEIGHT = 1.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        student, teacher = taps["student"], taps["teacher"]
        k = student.shape[1]
        rows_s = student.movedim(1, -1).reshape(-1, k)
        rows_t = teacher.movedim(1, -1).reshape(-1, k)
        mask = voxel_mask(taps["target"], self.params.voxels, self.ignore_index)
        if mask is not None:
            rows_s, rows_t = rows_s[mask.reshape(-1)], rows_t[mask.reshape(-1)]
        p = self.params
        return dist(rows_s, rows_t, p.beta, p.gamma, p.temperature)


register_objective("kd", KD, description="vanilla KD: per-voxel KL of softened class distributions (T² scaled)",
               paper="Hinton et al. 2015; SCPNet Table 4, Scribble2Scene Table 5", equation="T² · mean_v KL(softmax(t_v/T) ‖ softmax(s_v/T))",
               shapes="(B, K, X, Y, Z) logits, student and teacher")
register_objective("dist", DIST, description="DIST: Pearson correlation of class distributions, inter- and intra-class",
               paper="Huang et al., NeurIPS 2022; Scribble2Scene Table 5",
               equation="T²(β(1 − mean_v ρ(p_s,v, p_t,v)) + γ(1 − mean_k ρ(p_s,:k, p_t,:k)))",
               shapes="(B, K, X, Y, Z) logits; rows = selected voxels")
