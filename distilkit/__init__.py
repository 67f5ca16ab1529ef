"""distilkit: knowledge distillation for 3D semantic scene completion.

`import distilkit` is cheap (no torch). The layout follows one run:

* ``recipe.py`` — the recipe schema; ``registry.py`` — every named component (adapters, objectives, task losses,
  datasets, metrics, optimizers, schedules, connectors, hooks, recorders) and the ``distilkit.plugins`` entry point;
* ``data/`` — datasets, each describing itself (``info.py``: classes, grid, cameras) and collating its typed
  ``Batch`` (``batch.py``); ``samples.py`` gives every sample its id;
* ``structures.py`` — VoxelGrid, SparseVoxels, PointCloud; ``adapter.py`` — how a model is seen: inputs, taps,
  prediction tap; ``taps.py`` — the registered tap kinds and their checks;
* ``term.py`` — the contract of every loss term: ``losses/`` (pure functions and the task losses) and
  ``objectives/`` (distillation objectives, connectors) implement it;
* ``engine/`` — ``resolve`` checks a recipe; ``pipeline`` orders, hashes (``identity``) and locks its stages;
  ``stage`` runs one: build (``runs``: models from upstream runs; ``loader``: batches), loop (``trainer``: one
  step; ``hooks``), evaluate (``evaluate`` with ``metrics/``), publish (``checkpoints``, ``predictions``);
* ``report/`` — run, recipe, seed and comparison reports; ``sweep/`` — variants over seeds;
* ``geometry/`` — shared numerics (voxel alignment, kNN); ``files.py`` — atomic writes; ``cli.py`` — the command
  line.
"""

__version__ = "0.1.0"

from distilkit.repro import set_environment as _set_environment

_set_environment()  # MKL's and cuBLAS's reproducibility, read when they first run (DISTILKIT_DETERMINISTIC=0 opts out)

__all__ = ["__version__"]
