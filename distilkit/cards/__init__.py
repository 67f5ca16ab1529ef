"""What a recipe is checked against, declared without torch: each built-in component's card (its parameters, taps,
roles and metadata) and its registration, the implementation named by ``"module:attr"`` and imported only when the
component runs (:meth:`distilkit.registry.Registry.declare`). ``distilkit validate --static`` and ``distilkit sweep
--plan`` read cards only, so they start without importing torch.

An implementation subclasses its card (``class KD(KDCard, MultiTapObjective)``), so everything a card declares is
the component's own, written once.
"""
