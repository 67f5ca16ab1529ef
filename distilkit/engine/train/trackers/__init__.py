"""Experiment trackers: the recipe's ``trackers`` (``[tensorboard, {wandb: {mode: offline}}, mlflow, trackio]``) are
lifecycle hooks of every stage, each receiving the run's identity and resolved configuration, the same values at
the same steps, the report's files and the final scores (:mod:`~distilkit.engine.train.trackers.base`). The
built-in ones — ``tensorboard`` (:mod:`distilkit.engine.train.tensorboard`), ``wandb``, ``mlflow``, ``trackio`` —
import their library only when a run uses them; each is an optional extra (``pip install 'distilkit[wandb]'``).
They are declared, with their parameters and checks, in :mod:`distilkit.cards.trackers` (torch-free)."""

from distilkit.engine.train.trackers import to_mlflow, to_trackio, to_wandb  # noqa: F401
