"""Running stages: the pipeline (stages in dependency order, cached by identity, locked), one stage's run (build,
loop, evaluate, publish) over what the recipe's stages share (:mod:`~distilkit.engine.train.context`), the trainer
(one optimisation step), batches and loaders, optimizers and schedules, evaluation, randomness, processes, stopping
on request and running out of memory. Uses :mod:`~distilkit.engine.assemble`, :mod:`~distilkit.engine.store`,
:mod:`~distilkit.engine.hooks` and the library's lower layers; never :mod:`~distilkit.engine.memory`."""
