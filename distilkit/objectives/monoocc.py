"""MonoOcc's distillation terms as objectives (Zheng et al., ICRA 2024; release ``utils/ssc_loss.py``): the
privileged branch's voxel features into the monocular branch's (``monoocc_kl``) and its image features
(``monoocc_image``). The maths is :mod:`distilkit.losses.monoocc`'s."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from distilkit.cards.objectives.monoocc import ImageCard, KLCard
from distilkit.choices import Choice
from distilkit.data.batch import Batch
from distilkit.errors import TapError
from distilkit.losses.monoocc import monoocc_image, monoocc_kl
from distilkit.objectives.base import MultiTapObjective, Objective
from distilkit.objectives.common import occupied_at, release_labels

_NO_PAPER = "not available to us (the stored copy holds the abstract)"


class VoxelKL(KLCard, MultiTapObjective):
    """MonoOcc's voxel-feature distillation: per sample, at the voxels of the feature volume whose block of labels
    holds a class (VoxFormer's downsampled labels, not 0 nor 255), the KLDivLoss mean over those voxels and the
    channels; averaged over the batch; weight 2 (MonoOcc-L's ``ratio_distill``). ``form: raw`` is the release's KL
    on the raw features, ``softmax`` (default) the divergence of each voxel's channel distribution."""

    CHOICES = (Choice("what the KL compares", "each voxel's channels as a distribution (softmax), KL(p_T || p_S)",
                      _NO_PAPER, "KLDivLoss(log_target=True) on the raw features: sum exp(t) (t - s) / (C n), linear "
                      "in the student (its gradient -exp(t) / (C n) whatever s is), no minimum at s = t",
                      "`params: {form: raw}`"),
               Choice("the batch", "each sample's own mask and mean, averaged over the batch", _NO_PAPER,
                      "one sample: squeeze(), img_metas[0]'s labels for every sample (B > 1 fails)", ""),
               Choice("a sample with nothing to compare", "0", _NO_PAPER, "NaN (a mean over no element)"),
               Choice("the teacher", "any model with a volume tap of the student's shape, run live or stored",
                      _NO_PAPER, "features dumped to disk by a privileged MonoOcc (temporal frames, a large image "
                      "backbone; its config and files are not released)", ""))

    def compute(self, taps: dict[str, Any], batch: Batch) -> Tensor:
        s, t = taps["student"], taps["teacher"].detach()
        if s.shape != t.shape:
            raise TapError(f"monoocc_kl: the student's volume {tuple(s.shape)} and the teacher's {tuple(t.shape)} "
                           "differ (give the term a connector, or taps of one shape)")
        mask = occupied_at(release_labels(taps["target"], self.ignore_index), tuple(s.shape[2:]))
        return monoocc_kl(s, t, mask, self.params.form)


class ImageCosine(ImageCard, Objective):
    """MonoOcc's image-feature distillation: 1 - the mean over the pixels of cos(f_S, f_T) over the channels, the
    teacher's map resized to the student's (bilinear, corners aligned); weight 2 (``ratio_2d_distill``). Off in
    every released config; there the student's 128 channels pass an MLP 128 -> 256 -> 512 with a ReLU after each
    layer to the teacher's 512 (``connector: mlp`` is distilkit's nearest: as wide as the wider side, 512, and no
    ReLU after its second layer)."""

    CHOICES = (Choice("whether it runs", "when a recipe names it", _NO_PAPER,
                      "off in every config (use_large_model=False; its teacher features are not loaded)", ""),)

    def forward(self, student: Tensor, teacher: Tensor, batch: Batch) -> Tensor:
        return monoocc_image(student, teacher.detach())


__all__ = ["ImageCosine", "VoxelKL"]
