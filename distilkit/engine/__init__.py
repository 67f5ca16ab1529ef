"""The engine: from a resolved recipe to trained, scored and published stages. Its rooms, from the bottom up (each
may use the rooms below it and the library's lower layers — the recipe, the registries, data, objectives, metrics,
reports — never a room above; ``pyproject.toml``'s import-linter contracts check it):

* :mod:`~distilkit.engine.store` — what a run leaves on disk and how it is named: checkpoints, locks, stage
  identities, published predictions;
* :mod:`~distilkit.engine.hooks` — the training loop's lifecycle hooks and the public view of the loop (a plugin
  contract: its path is documented);
* :mod:`~distilkit.engine.assemble` — from a recipe to its resolved stages and their models: resolution, models rebuilt
  from runs, recorded taps, the checks ``validate`` makes of data and weights files;
* :mod:`~distilkit.engine.train` — running stages: the pipeline, one stage's run, the trainer, loaders, optimizers,
  evaluation, randomness, processes, stopping on request, running out of memory;
* :mod:`~distilkit.engine.memory` — a training step's memory, estimated before training (uses the trainer; the
  trainer never uses it);
* :mod:`~distilkit.engine.infer` — what is done with a finished run: ``predict``, ``complete``, ``export``.

docs/development/architecture.md draws the whole house.
"""
