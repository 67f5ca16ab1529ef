"""Cards of MonoOcc's distillation terms (Zheng et al., ICRA 2024): the voxel-feature KL and the image-feature
cosine (:mod:`distilkit.objectives.monoocc`)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from distilkit.cards.base import Match, ObjectiveCard, declare_objective
from distilkit.cards.objectives.common import NoParams

_PAPER = "MonoOcc (Zheng et al., ICRA 2024, arXiv 2403.08766), utils/ssc_loss.py"


class KLParams(BaseModel):
    model_config = ConfigDict(extra="forbid")
    form: Literal["softmax", "raw"] = Field(
        "softmax", description="softmax: KL between each voxel's channel distributions (softmax over the channels); "
                               "raw: the release's KLDivLoss(log_target=True) on the features as they are, "
                               "exp(t) (t - s): linear in the student, no minimum at the teacher")


class KLCard(ObjectiveCard):
    """MonoOcc's voxel-feature distillation (card of :class:`distilkit.objectives.monoocc.VoxelKL`), weight 2."""

    Params = KLParams
    MATCH = {"teacher": Match("equal", "same", on_labels=True)}
    CONSUMES = {"student": "volume_features", "teacher": "volume_features"}
    BATCH = {"target": "voxel_target"}
    DEFAULT_WEIGHT = 2.0

    @classmethod
    def teacher_voxels(cls, params: BaseModel) -> dict[str, str]:
        return {"teacher": "occupied"}  # the blocks of labels holding a class


class ImageCard(ObjectiveCard):
    """MonoOcc's image-feature distillation (card of :class:`distilkit.objectives.monoocc.ImageCosine`), weight 2."""

    Params = NoParams
    MATCH = {"teacher": Match("equal", "resampled")}  # the teacher's map resized to the student's
    CONSUMES = {"student": "image_features", "teacher": "image_features"}
    DEFAULT_WEIGHT = 2.0


declare_objective("monoocc_kl", "distilkit.objectives.monoocc:VoxelKL", KLCard,
                  description="MonoOcc's voxel-feature KL at the blocks holding a class (softmax over channels; raw: "
                              "the release)",
                  paper=_PAPER,
                  equation="mean_b 1/(C n_b) Σ_{v occupied} Σ_c p_T (log p_T − log p_S); raw: exp(t)(t − s)",
                  shapes="(B, C, X, Y, Z) volumes of one shape (labels pooled to them)")
declare_objective("monoocc_image", "distilkit.objectives.monoocc:ImageCosine", ImageCard,
                  description="MonoOcc's image-feature distillation: 1 − mean cosine, the teacher resized",
                  paper=_PAPER,
                  equation="1 − mean_{pixels} cos(f_S, resize(f_T))",
                  shapes="(B, C, H, W) student, (B, C, h, w) teacher (a connector for other channels)")

__all__ = ["ImageCard", "KLCard", "KLParams"]
