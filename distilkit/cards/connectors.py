"""The built-in connectors, declared without torch (:mod:`distilkit.objectives.connectors` builds them): ``linear``
(also ``conv1x1``), ``mlp``, ``conv3``, ``height_max`` and ``height_mean``."""

from __future__ import annotations

from distilkit.registry import CONNECTORS

CONNECTORS.declare("linear", "distilkit.objectives.connectors:_linear", card=None,
                   description="1x1 convolution on maps, linear layer on rows and sparse voxels",
                   paper="FitNets' regressor (Romero et al., ICLR 2015)")
CONNECTORS.alias("conv1x1", "linear")
CONNECTORS.declare("mlp", "distilkit.objectives.connectors:_mlp", card=None,
                   description="two linear layers (1x1 on maps) with a ReLU, as wide as the wider side", paper="—")
CONNECTORS.declare("conv3", "distilkit.objectives.connectors:_conv3", card=None,
                   description="a 3x3 (3-D: 3x3x3) convolution on dense maps", paper="—")
CONNECTORS.declare("height_max", "distilkit.objectives.connectors:_height_max", card=None,
                   description="voxel features (dense or sparse) max-pooled over height onto the (X, Y) plane, then a "
                               "1x1 convolution: a 3-D student against a bird's-eye teacher",
                   paper="the voxel-to-BEV release's column scatter-max (Jiang et al., arXiv 2304.11393)")
CONNECTORS.declare("height_mean", "distilkit.objectives.connectors:_height_mean", card=None,
                   description="voxel features (dense or sparse) averaged over height onto the (X, Y) plane, then a "
                               "1x1 convolution",
                   paper="—")
