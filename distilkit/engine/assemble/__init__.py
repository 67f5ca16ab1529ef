"""From a recipe to what a run builds: the recipe resolved against the registries (every name, parameter, tap and
field checked before any data or model exists), models built from resolved specs or rebuilt from a stage's run folder
(with the recipe's recorded taps), and the checks ``validate`` makes of the data and the weights files. Uses
:mod:`~distilkit.engine.store` and the library's lower layers; nothing that trains."""
