"""L2COcc's distillation terms as objectives (Wang et al., IROS 2025; release ``CameraSegmentor.py``): prediction
alignment (``l2cocc_pad``), numeric feature similarity (``l2cocc_fsd``) and relational feature similarity
(``l2cocc_relation``), on any pair whose taps have the kinds (the release: a LiDAR teacher, a camera student)."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.l2cocc import l2cocc_fsd, l2cocc_pad, l2cocc_relation
from distilkit.objectives.base import MultiTapObjective, register_objective
from distilkit.objectives.common import occupied_at, release_labels

_EMPTY_NAN = Choice("a sample (or map) with nothing to align", "0", "not stated",
                    "NaN (KLDivLoss and .mean() over no element)")


class PADParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    include_empty: bool = Field(False, description="also the empty voxels (label 0): the release's distill_kl_empty")


class PAD(MultiTapObjective):
    """L2COcc's prediction alignment: per sample the mean over valid non-empty voxels and classes of
    KL(p_T || p_S) (the release's ``KLDivLoss(reduction="mean")``), averaged over the batch; weight 70 as its
    configs."""

    CHOICES = (_EMPTY_NAN,)
    Params = PADParams
    CONSUMES = {"student": "voxel_logits", "teacher": "voxel_logits"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 70.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        return l2cocc_pad(taps["student"], taps["teacher"], labels, self.params.include_empty)


class NoParams(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FSD(MultiTapObjective):
    """L2COcc's numeric feature similarity: the mean of 1 - cos(f_S, f_T) over the feature map's positions whose
    block of the label grid holds an occupied voxel; weight 4 as its configs (it computes per-layer ratios and never
    uses them). Student and teacher maps of one shape and width (a ``connector`` where the widths differ)."""

    CHOICES = (_EMPTY_NAN, Choice("per-layer ratios", "none (one map per term; add a term per map)", "not stated",
                                  "computed (0.1, 1, 0.5, 1.5) and never applied"))
    Params = NoParams
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 4.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        s, t = taps["student"], taps["teacher"]
        if s.shape != t.shape:
            from distilkit.errors import TapError

            raise TapError(f"l2cocc_fsd: student map {tuple(s.shape)} and teacher map {tuple(t.shape)} differ "
                           "(give the term a connector, or taps of one shape)")
        mask = occupied_at(release_labels(taps["target"], self.ignore_index), tuple(s.shape[2:]))
        return l2cocc_fsd(s, t.detach(), mask)


class Relation(MultiTapObjective):
    """L2COcc's relational feature similarity: the mean L1 distance between the student's and the teacher's P x P
    cosine matrices among the map's positions (computed in row blocks: O(P^2 C) time, no P x P matrix); weight 5
    as its configs (the release sums it over the three TPV planes' first neck maps: one term per map here)."""

    CHOICES = (Choice("which maps", "the recipe's feature-map taps (one term each)", "the TPV planes' features",
                      "the first neck output of each TPV plane, summed", ""),)
    Params = NoParams
    CONSUMES = {"student": "feature_map", "teacher": "feature_map"}
    DEFAULT_WEIGHT = 5.0

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return l2cocc_relation(taps["student"], taps["teacher"].detach())


register_objective("l2cocc_pad", PAD, description="L2COcc's prediction alignment: per-sample KLDivLoss mean over "
                   "valid non-empty voxels", paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                   equation="mean_b 1/(n_b K) Σ_{v valid, non-empty} Σ_k p_T (log p_T − log p_S)",
                   shapes="(B, K, X, Y, Z) logits, student and teacher")
register_objective("l2cocc_fsd", FSD, description="L2COcc's numeric feature similarity: 1 − cos over occupied "
                   "positions", paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                   equation="mean_{p occupied} (1 − cos(f_S,p, f_T,p))",
                   shapes="(B, C, X, Y[, Z]) maps of one shape; labels pooled to the map")
register_objective("l2cocc_relation", Relation, description="L2COcc's relational similarity: L1 between P×P "
                   "cosine matrices, in row blocks", paper="L2COcc (Wang et al., IROS 2025), CameraSegmentor.py",
                   equation="mean_{b,i,j} |cos_S(i,j) − cos_T(i,j)|",
                   shapes="(B, C_s / C_t, X, Y[, Z]) maps of one spatial size")
