"""The built-in connectors, declared without torch (:mod:`distilkit.objectives.connectors` builds them): ``linear``
(also ``conv1x1``), ``mlp`` and ``conv3``."""

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
