"""A training step's memory, estimated before training (``distilkit validate``): the stage's real step run on a
small copy of its data (:mod:`~distilkit.engine.memory.probe`) and extrapolated
(:mod:`~distilkit.engine.memory.estimate`). Uses the trainer; the trainer never uses it (the error a stage raises
when it runs out of memory is :mod:`distilkit.engine.train.oom`'s)."""
