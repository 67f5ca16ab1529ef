"""Distillation-DPO (Zhang et al., arXiv 2504.11447; happyw1nd/DistillationDPO): preference pairs of the student's own
completions, scored against the ground truth, steer a VSD-style score distillation."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from distilkit.cards.objectives.dpo import DistillationDPOCard, DPOParams
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.losses.dpo import distillation_dpo
from distilkit.metrics.points import chamfer_distance, jsd_3d, jsd_bev
from distilkit.objectives.score import VSD, VSDParams
from distilkit.structures import PointCloud

RANKINGS = {"chamfer": chamfer_distance, "jsd": jsd_bev, "jsd_3d": jsd_3d}  # lower is better


class DistillationDPO(DistillationDPOCard, VSD):
    """Each step: the student's ``samples`` (from its ``start_noise`` eps) and a second completion of the same scans
    from ``noise_scale`` eps (the student's ``generate``); per scene the one closer to the ground truth (``rank_by``)
    is the winner. Two auxiliary score networks (copies of the teacher, as the release; ``aux: lora`` for LoRAs; one
    optimizer) fit winners and losers of a fresh pair the student generates without gradient (the release's aux step;
    ``aux_sample: same``: this step's pair), before the student's step by default; the student's winner and loser are
    re-noised with one t and eps, and :func:`distilkit.losses.distillation_dpo` moves the winner towards the
    teacher's score and away from its auxiliary network's, the loser the other way (``sign: release``, the code's
    choice; ``sign: paper`` is eq. 16-18 as printed, the opposite), linearly or bounded by ``beta``."""

    CHOICES = (
        Choice("the sign", "the winner towards the teacher's score, the loser away (`sign: release`)",
               "eq. 16-18 print the opposite (winner away, loser towards)", "DistillationDPO.py lines 485-486: the "
               "release's sign (with a zero gradient: the VSD stop-gradient mistake)", "`sign: paper`"),
        Choice("the loss's form", "linear in the implicit log-ratios (the release's)", "eq. 16-18: the gradient only",
               "linear", "`beta`: Diffusion-DPO's log-sigmoid, bounded"),
        Choice("EMD", "the `emd` metric: exact, on 2,048-point subsamples", "reported (Table 1)",
               "Sinkhorn with epsilon 0.001 m on 0.5 m voxels: its kernel underflows (not an EMD)"),
    )

    def setup(self, taps: dict[str, Any], batch: Batch) -> None:
        super().setup(taps, batch)
        self.aux_loser = self._aux_copy()
        self._win_rate: list[float] = []

    def aux_networks(self) -> list[nn.Module]:
        return [self.aux, self.aux_loser]

    def pair(self, first: Tensor, second: Tensor, target: PointCloud) -> tuple[Tensor, Tensor, Tensor]:
        """(winner, loser, first_wins (B,)) per scene, by ``rank_by`` against the target (no gradient in the
        choice; each output keeps the gradient of the completion it came from)."""
        rank = RANKINGS[self.params.rank_by]
        first_wins = torch.tensor([rank(first[b], target.cloud(b)) <= rank(second[b], target.cloud(b))
                                   for b in range(first.shape[0])], device=first.device)
        pick = first_wins[:, None, None]
        return torch.where(pick, first, second), torch.where(pick, second, first), first_wins

    def fit_pair(self, winner: Tensor, loser: Tensor, taps: dict[str, Any]) -> None:
        """The auxiliary networks' step: on a fresh pair of the student (``aux_sample: fresh``, the release) ranked
        like the student's own, or on the given one."""
        if self.params.aux_sample == "fresh":
            cond = taps["condition"]
            noise = torch.randn_like(winner)
            first, second = self.fresh(noise, cond), self.fresh(self.params.noise_scale * noise, cond)
            winner, loser, _ = self.pair(first, second, PointCloud(taps["target"], taps["target_lengths"]))
        self.fit_aux([(self.aux, winner.detach()), (self.aux_loser, loser.detach())], taps["condition"])

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        student = self.context.student  # type: ignore[union-attr]  (its generate(): checked by the recipe)
        first = taps["student"].points
        second = student.generate(taps["condition"], self.params.noise_scale * taps["noise"].points)
        winner, loser, first_wins = self.pair(first, second, PointCloud(taps["target"], taps["target_lengths"]))
        self._win_rate.append(float(first_wins.float().mean()))
        if self.params.aux_update == "before":
            self.fit_pair(winner, loser, taps)
        self._pending = (winner.detach(), loser.detach())
        with torch.no_grad():
            x_w, t, eps = self._noised(winner.detach())
            x_l = loser.detach() + (x_w - winner.detach())  # the same t and eps for both
            teacher, cond = self.context.teacher, taps["condition"]  # type: ignore[union-attr]
            preds = (teacher.predict_noise(x_w, t, cond), self.aux.predict_noise(x_w, t, cond),
                     teacher.predict_noise(x_l, t, cond), self.aux_loser.predict_noise(x_l, t, cond))
        return distillation_dpo(winner, loser, *preds, weight=self._weight(t), sign=self.params.sign,
                                beta=self.params.beta, noise_w=eps)

    def update(self, step: int, batch: Batch, taps: dict[str, Any]) -> dict[str, float]:
        if self.params.aux_update == "after":
            winner, loser = self._pending
            self.fit_pair(winner, loser, taps)
        values, self._aux_losses = self._aux_losses, []
        rate, self._win_rate = self._win_rate, []
        out = {"dpo_first_wins": sum(rate) / len(rate)} if rate else {}
        return {**out, **({"dpo_aux_loss": sum(values) / len(values)} if values else {})}


__all__ = ["RANKINGS", "DPOParams", "DistillationDPO", "VSDParams"]
