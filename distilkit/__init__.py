"""distilkit: knowledge distillation for 3D semantic scene completion.

`import distilkit` is cheap (no torch). The layout follows one run:

* ``recipe.py`` — the recipe schema; ``registry.py`` — every named component (adapters, objectives,
  task losses, datasets, metrics) and the ``distilkit.plugins`` entry point;
* ``data/`` — datasets, each describing itself (``info.py``: classes, grid, cameras) and collating its
  typed ``Batch`` (``batch.py``);
* ``adapter.py`` — how a model is seen: inputs, taps, prediction tap; ``taps.py`` — the registered tap
  kinds and their checks;
* ``term.py`` — the contract of every loss term: ``losses/`` (pure functions and the task losses) and
  ``objectives/`` (distillation objectives, connectors) implement it;
* ``engine/`` — ``resolve`` checks a recipe, ``pipeline`` runs its stages, ``models`` builds them,
  ``trainer`` (+ ``hooks``, ``recorders``) trains one, ``evaluate`` scores it with ``metrics/``, and
  ``report``/``seeds`` (via ``scores``) show the results;
* ``geometry/`` — shared numerics (voxel grids and alignment, kNN); ``cli.py`` — the command line.
"""

__version__ = "0.1.0"

from distilkit.repro import set_environment as _set_environment

_set_environment()  # MKL's and cuBLAS's reproducibility, read when they first run (DISTILKIT_DETERMINISTIC=0 opts out)

__all__ = ["__version__"]
