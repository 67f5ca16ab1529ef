"""LiCROcc's distillation terms as objectives (Ma et al., RA-L 2025; release ``ssc_rs.py``): predictive
distribution (``licrocc_kl``, PDD), cross-modal residual (``licrocc_bev``, CMRD) and BEV relation
(``licrocc_affinity``, BRD), on any pair whose taps have the kinds (the release: a LiDAR + camera teacher, a radar
student; here a bird's-eye tap of any voxel tap: ``taps: {bev: {of: completion, kind: bev_features, collapse:
max}}``). The maths is :mod:`distilkit.losses.licrocc`'s."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.objectives.licrocc import _EXTRA, MAX_MAPS, AffinityCard, BEVCard, KLCard
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.errors import DistilkitError, TapError
from distilkit.losses.licrocc import licrocc_affinity, licrocc_bev, licrocc_kl
from distilkit.objectives.base import MultiTapObjective
from distilkit.objectives.common import map_pairs, occupied_at, release_labels

_NO_PAPER = "not available to us (the stored copy holds the abstract)"
_EMPTY = Choice("a sample (or map) with nothing to compare", "0", _NO_PAPER, "NaN (a mean over no element)")
_SCENES = Choice("scenes 'not useful' (night, rain)", "every sample weighs 1", _NO_PAPER,
                 "x1e-5 on PDD and CMRD per sample, never applied: its dataset sets every scene useful (L335)",
                 "`params: {unuseful_weight: 1.0e-5}` with a batch field `scene_useful`")
_AUTO = Choice("automatic loss weights", "off: the recipe's weights", _NO_PAPER,
               "AutomaticWeightedLoss (0.5 / sigma^2 per term, its log(1 + sigma^2) commented out) is never built: "
               "distill_len = 0 is hard-coded (L107)", "`params: {auto_weight: release}`")
_MODE = Choice("the frozen teacher's mode", "eval (`teacher: {mode: eval}`)", _NO_PAPER,
               "train: frozen parameters, nothing calls .eval(): BatchNorm batch statistics and its Dropout(0.5) "
               "before the output layer are on", "`teacher: {mode: train}`")


class _AutoWeighted(MultiTapObjective):
    """A term with the release's automatic weight as an option: 0.5 / sigma^2 times the term (``release``), sigma
    learned with the student, initially 1, without a regulariser (the release's class has its log(1 + sigma^2)
    commented out)."""

    def __init__(self, params: Any) -> None:
        super().__init__(params)
        self.sigma = nn.Parameter(torch.ones(())) if params.auto_weight != "off" else None

    def weighted(self, loss: Tensor) -> Tensor:
        if self.sigma is None:
            return loss
        return 0.5 / self.sigma.to(loss.dtype) ** 2 * loss

    def scene_weights(self, batch: Batch, like: Tensor) -> Tensor | None:
        """The batch's per-sample weights: 1, or ``unuseful_weight`` where ``scene_useful`` is false."""
        if self.params.unuseful_weight == 1.0:
            return None
        flags = batch.meta.get("scene_useful")
        if flags is None:
            raise DistilkitError(f"{type(self).__name__}: unuseful_weight is {self.params.unuseful_weight:g} but the "
                                 "batch has no scene_useful flag (the data must say which scenes are useful)")
        return torch.tensor([1.0 if bool(f) else self.params.unuseful_weight for f in flags], dtype=like.dtype,
                            device=like.device)


class PDD(KLCard, _AutoWeighted):
    """LiCROcc's predictive distribution distillation: per sample the mean over the voxels with a class label (not
    empty, not ignored) and the classes of KL(p_T || p_S) (the release's ``KLDivLoss(reduction="mean")``), times
    the sample's scene weight, averaged over the batch; weight 10 (its ``ratio_distill``)."""

    CHOICES = (_EMPTY, _SCENES, _AUTO, _MODE)

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        s = taps["student"]
        labels = release_labels(taps["target"], self.ignore_index)
        return self.weighted(licrocc_kl(s, taps["teacher"].detach(), labels, self.scene_weights(batch, s)))


class CMRD(BEVCard, _AutoWeighted):
    """LiCROcc's cross-modal residual distillation: per sample and bird's-eye map pair the mean of 1 - cos(f_S, f_T)
    over the cells whose column holds a labelled occupied voxel (the labels pooled to the map), times the scene
    weight, averaged over the maps and the samples; weight 4 (hard-coded in the release, not its
    ``ratio_distill``). The release pairs the student's residual (its myMLP output) with the teacher's fused map at
    three scales: name the taps (``student_2``/``teacher_2``, ``student_3``/``teacher_3``)."""

    CHOICES = (_EMPTY, _SCENES, _AUTO,
               Choice("the occupied-cell mask", "the labels' columns at the map's cells", _NO_PAPER,
                      "indexed [x, y] on features laid [y, x] (L510-524): transposed on its square maps",
                      "`params: {transpose_mask: true}`"),
               Choice("the mask's labels", "a cell is kept where its block of columns holds a voxel with a class",
                      _NO_PAPER, "majority-vote downsampled labels (target_1_2/4/8), 255 set to 0: a coarse voxel "
                      "whose majority is nuScenes' noise label drops out", ""))

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        labels = release_labels(taps["target"], self.ignore_index)
        students, teachers, masks = [], [], []
        for s_role, t_role in map_pairs(taps, _EXTRA, "licrocc_bev"):
            s, t = taps[s_role], taps[t_role].detach()
            if s.shape != t.shape:
                raise TapError(f"licrocc_bev: {s_role} map {tuple(s.shape)} and {t_role} map {tuple(t.shape)} differ "
                               "(give the term a connector, or taps of one shape)")
            mask = occupied_at(labels, tuple(s.shape[2:]))
            if self.params.transpose_mask:
                if s.shape[2] != s.shape[3]:
                    raise TapError(f"licrocc_bev: transpose_mask needs square maps, got {tuple(s.shape[2:])}")
                mask = mask.transpose(1, 2)
            students.append(s)
            teachers.append(t)
            masks.append(mask)
        return self.weighted(licrocc_bev(students, teachers, masks, self.scene_weights(batch, students[0])))


class BRD(AffinityCard, _AutoWeighted):
    """LiCROcc's BEV relation distillation: each bird's-eye map of both models resized to ``size`` (bilinear), the
    L1 mean between the two models' cosine self-affinities (exact, in tiles), summed over the map pairs; weight 40
    (the release's ratio_distill 10 x 4). The release divides each map's mean by B again (``release_batch``)."""

    CHOICES = (_AUTO,
               Choice("the batch reduction", "the mean over the B P^2 entries", _NO_PAPER,
                      "F.l1_loss (mean) / B: the weight is 40 / B per sample (B = 4 per GPU)",
                      "`params: {release_batch: true}`"),
               Choice("which maps", "the recipe's map pairs (up to 3)", _NO_PAPER,
                      "x3_f, x4_f and x5 (not x2_f, which CMRD reads), each resized to x5's 32 x 32", ""))

    def scene_weights(self, batch: Batch, like: Tensor) -> Tensor | None:
        return None

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        pairs = map_pairs(taps, _EXTRA, "licrocc_affinity")
        return self.weighted(licrocc_affinity([taps[s] for s, _ in pairs], [taps[t].detach() for _, t in pairs],
                                              self.params.size, self.params.release_batch))


__all__ = ["BRD", "CMRD", "MAX_MAPS", "PDD"]
