"""The files VoxFormer's ``size: paper`` network (:mod:`.release`) reads.

**A released VoxFormer checkpoint** (mmdet's ``{"state_dict": ...}``, e.g. VoxFormer-S's): ``img_backbone.*`` (mmdet's
ResNet-50, torchvision's names), ``img_neck.*`` (the FPN) and ``pts_bbox_head.*`` are the network's under ``net.``.
Reported as left out by design: ``img_backbone.layer4.*`` (mmdet builds the fourth stage, ``out_indices=(2,)``
reads the third) and ``pts_bbox_head.self_transformer.level_embeds`` / ``cams_embeds`` (the self-attention reads no
image). Every other key that does not fit is named by ``load_weights``, as the model calls it and as the file
spells it.

**torchvision's ResNet-50 ImageNet weights** (``resnet50-19c8e357.pth``, the file VoxFormer's configs load) for the
image encoder alone. The file is a bare state dict in torchvision's names (``conv1.weight``, ``bn1.*``,
``layer1.0.conv1.weight``, ..., ``fc.*``). It is read into ``net.img_backbone.*`` as
:class:`~distilkit.weights.PartialWeights`: every
weight of the backbone must be there and fit (each misfit named), the rest of the model keeps its initial weights.
Two things are accepted by design and said in the log: the file predates the batch norms' ``num_batches_tracked``
(torchvision's original release), so a missing counter is set to 0; and ``fc.*`` (the ImageNet classifier) and
``layer4.*`` (the fourth stage, which VoxFormer does not read) have no place in the encoder and are ignored. Any
other key of the file is unexpected and named.
"""

from __future__ import annotations

from typing import Any

import torch

from distilkit.weights import PartialWeights, under_prefix

SCOPE = "net.img_backbone."
UNUSED = ("fc.", "layer4.")
RELEASE = ("img_backbone.", "img_neck.", "pts_bbox_head.")
NOT_THE_NETWORK = {"img_backbone.layer4.": "the fourth stage: out_indices=(2,) reads the third",
                   "pts_bbox_head.self_transformer.level_embeds": "the self-attention reads no image",
                   "pts_bbox_head.self_transformer.cams_embeds": "the self-attention reads no image"}


def is_torchvision_resnet(weights: dict[str, Any]) -> bool:
    """A torchvision ResNet state dict: its stem and first block under their bare names."""
    return "conv1.weight" in weights and "layer1.0.conv1.weight" in weights


def from_torchvision(weights: dict[str, Any]) -> dict[str, Any]:
    """``weights`` as they are when they are not a torchvision ResNet's, else the backbone's (see the module)."""
    if not is_torchvision_resnet(weights):
        return weights
    out: dict[str, Any] = {}
    ignored = sorted({k.split(".")[0] + ".*" for k in weights if k.startswith(UNUSED)})
    for key, value in weights.items():
        if key.startswith(UNUSED):
            continue
        out[SCOPE + key] = value
        if key.endswith(".running_var"):  # a batch norm: its step counter, which the original file lacks
            counter = key[: -len("running_var")] + "num_batches_tracked"
            if counter not in weights:
                out[SCOPE + counter] = torch.tensor(0, dtype=torch.long)
    return PartialWeights(out, SCOPE, tuple(ignored))


def from_mmdet(weights: dict[str, Any]) -> dict[str, Any]:
    """``weights`` as they are when they are not a VoxFormer release's, else under the network's names."""
    return under_prefix(weights, RELEASE, NOT_THE_NETWORK)


__all__ = ["SCOPE", "from_mmdet", "from_torchvision", "is_torchvision_resnet"]
