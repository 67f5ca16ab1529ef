"""Card of Distillation-DPO (Zhang et al., arXiv 2504.11447) (:mod:`distilkit.objectives.dpo`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from distilkit.cards.base import declare_objective
from distilkit.cards.objectives.score import VSDCard, VSDParams


class DPOParams(VSDParams):
    noise_scale: float = Field(1.1, gt=0, description="the second completion starts from this multiple of the first "
                                                      "one's noise (the released code: 1.1)")
    rank_by: Literal["chamfer", "jsd", "jsd_3d"] = Field(
        "chamfer", description="the completion with the lower value against the ground-truth scene wins: LiDiff's "
                               "Chamfer distance (the released code's ranking), its BEV Jensen-Shannon distance, or the "
                               "3-D point-count one (jsd_3d: the released code's calc_jsd)")
    sign: Literal["release", "paper"] = Field(
        "release", description="release: the winner moves towards the teacher's score and the loser away (the released "
                               "DistillationDPO.py, lines 485-486; it distils); paper: eq. 16-18 as printed, both "
                               "gradients negated (distilkit.losses.distillation_dpo states the conflict)")
    beta: float | None = Field(
        None, gt=0, description="None: the linear surrogate (the release; unbounded in the log-ratios); beta > 0: "
                                "Diffusion-DPO's log-sigmoid with this beta on the implicit-reward margin, bounded: its "
                                "gradient vanishes once the winner leads by much more than 1 / beta")


class DistillationDPOCard(VSDCard):
    """Distillation-DPO (card of :class:`distilkit.objectives.dpo.DistillationDPO`): the student's ``generate``
    always (its second completion)."""

    Params = DPOParams
    TAP_HINTS = {"student": ("samples",), "noise": ("start_noise",)}
    CONSUMES = {"student": "points", "noise": "points"}
    BATCH = {"condition": "scan", "target": "scene", "target_lengths": "scene_lengths"}
    STUDENT_REQUIRES = frozenset({"generate"})
    VERSION = 2  # 2: copies as auxiliary networks fitted on a fresh pair; sign and beta


declare_objective("distillation_dpo", "distilkit.objectives.dpo:DistillationDPO", DistillationDPOCard,
                  description="Distillation-DPO: winner/loser pairs of the student's completions from eps and 1.1 "
                              "eps, two auxiliary score networks, VSD towards the winner and away from the loser (the "
                              "release's sign; the paper's eq. 16-18 print the opposite: sign: paper), linear or "
                              "bounded (beta)",
                  paper="Distillation-DPO (Zhang et al., arXiv 2504.11447), ScoreLiDAR's successor",
                  equation="∇ = s w(t)[(ε_T − ε_aux,w)(x_t^w) ∂x_w/∂θ − (ε_T − ε_aux,l)(x_t^l) ∂x_l/∂θ], s = +1 "
                           "(release) or −1 (paper eq. 16-18), times 2σ(−β s Δ) with beta; winner = lower CD to the "
                           "ground truth",
                  shapes="student samples and their start noise: points (B, M, 3); condition: the batch's scan; "
                         "target: its scene; teacher: predict_noise; student: generate")

__all__ = ["DPOParams", "DistillationDPOCard"]
