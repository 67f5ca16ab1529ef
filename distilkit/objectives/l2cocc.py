"""L2COcc's distillation terms as objectives (Wang et al., IROS 2025; release ``CameraSegmentor.py``): prediction
alignment (``l2cocc_pad``), numeric feature similarity (``l2cocc_fsd``) and relational feature similarity
(``l2cocc_relation``), on any pair whose taps have the kinds (the release: a LiDAR teacher, a camera student)."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from distilkit.cards.objectives.l2cocc import (_EXTRA, MAX_MAPS, FSDCard, FSDParams, NoParams, PADCard,
                                               PADParams, RelationCard)
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.l2cocc import l2cocc_fsd, l2cocc_pad, l2cocc_relation
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.common import map_pairs, occupied_at, release_labels

_EMPTY_NAN = Choice("a sample (or map) with nothing to align", "0", "not stated",
                    "NaN (KLDivLoss and .mean() over no element)")
_TEACHER_MODE = Choice("the frozen teacher's mode", "eval (`teacher: {mode: eval}`)", "not stated",
                       "train: the teacher is set to eval once, then PyTorch Lightning's .train() on the module "
                       "holding it switches it back (batch statistics, its Swin's drop-path 0.2 on; "
                       "tools/pl_model.py, CameraSegmentor.py)", "`teacher: {mode: train}` (recipes/sweeps/l2cocc.yaml)")


class PAD(PADCard, MultiTapObjective):
    """L2COcc's prediction alignment: per sample the mean over valid non-empty voxels and classes of
    KL(p_T || p_S) (the release's ``KLDivLoss(reduction="mean")``), averaged over the batch; weight 70 as its
    configs. Reduction: the mean of per-sample values, as the release at any batch size (its code divides the sum
    over samples by B; one sample per GPU under DDP gives the same)."""

    CHOICES = (_EMPTY_NAN,
               Choice("the batch reduction", "the mean of per-sample values", "not stated",
                      "the sum over the samples / B (and one sample per GPU, DDP averaging): the same", ""),
               _TEACHER_MODE)
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        return l2cocc_pad(taps["student"], taps["teacher"], labels, self.params.include_empty)


class FSD(FSDCard, MultiTapObjective):
    """L2COcc's numeric feature similarity: the mean of 1 - cos(f_S, f_T) over the feature map's positions whose
    block of the label grid holds an occupied voxel, per sample then over the batch (``reduce``); with several map
    pairs (``taps: {student, teacher, student_2, teacher_2, ...}``, up to 4) the mean over the maps before the
    weight, as the release (the sum over its 20 maps / 20, x4); weight 4 as its configs (it computes per-layer
    ratios and never uses them). Each pair of one shape and width (a ``connector`` projects the first student map
    only). More than 4 maps: several terms, each weighted 4 m / M for its m of the M maps."""

    CHOICES = (_EMPTY_NAN,
               Choice("per-layer ratios", "none: the mean over the term's maps", "not stated",
                      "computed (0.1, 1, 0.5, 1.5) and never applied: the sum over its maps / their number"),
               Choice("several maps", "the pairs of one term averaged before the weight 4 (the release's form)",
                      "not stated", "CameraSegmentor.py: 20 maps summed, / 20, x4 (0.2 per map); one term per map "
                      "at x4 gives M times the release", "`taps: {student_2: ..., teacher_2: ...}` (up to 4 pairs)"),
               Choice("the batch reduction", "the mean of per-sample values", "not stated",
                      "one sample per GPU (batch_size=1), DDP averaging: the mean of per-sample values; its code "
                      "pools the masked positions of a batch", "`reduce: pooled`"))
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        from distilkit.errors import TapError

        pairs = map_pairs(taps, _EXTRA, "l2cocc_fsd")
        labels = release_labels(taps["target"], self.ignore_index)
        students, teachers, masks = [], [], []
        for s_role, t_role in pairs:
            s, t = taps[s_role], taps[t_role]
            if s.shape != t.shape:
                raise TapError(f"l2cocc_fsd: {s_role} map {tuple(s.shape)} and {t_role} map {tuple(t.shape)} differ "
                               "(give the term a connector, or taps of one shape)")
            students.append(s)
            teachers.append(t.detach())
            masks.append(occupied_at(labels, tuple(s.shape[2:])))
        return l2cocc_fsd(students, teachers, masks, self.params.reduce)


class Relation(RelationCard, MultiTapObjective):
    """L2COcc's relational feature similarity: the mean L1 distance between the student's and the teacher's P x P
    cosine matrices among the map's positions (computed in tiles of the upper triangle, one GEMM each: O(P^2 C)
    time, no P x P matrix); weight 5 as its configs (the release sums it over the three TPV planes' first neck maps: one term per map here, each at
    x5, is the release's sum). Reduction: the mean over the B P^2 entries, which is the mean of per-sample values
    (every sample has P^2), as the release's one sample per GPU."""

    CHOICES = (Choice("which maps", "the recipe's feature-map taps (one term each)", "the TPV planes' features",
                      "the first neck output of each TPV plane, summed", ""),
               Choice("the batch reduction", "the mean over the B P^2 entries (= the mean of per-sample values)",
                      "not stated", "F.l1_loss over (B, P, P), one sample per GPU (DDP averaging): the same", ""))
    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        return l2cocc_relation(taps["student"], taps["teacher"].detach())


__all__ = ["FSD", "MAX_MAPS", "PAD", "FSDParams", "NoParams", "PADParams", "Relation"]
