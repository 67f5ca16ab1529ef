"""distilkit: knowledge distillation for 3D semantic scene completion.

`import distilkit` is cheap (no torch). The pieces live in submodules:
`distilkit.losses` (pure differentiable functions), `distilkit.objectives`,
`distilkit.metrics`, `distilkit.data`, `distilkit.engine`, and the command line in
`distilkit.cli`.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
