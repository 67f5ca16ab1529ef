"""distilkit's built-in adapters (installed as ``distilkit_adapters``), loaded through the
``distilkit.plugins`` entry point like any third-party plugin."""


def register() -> None:
    """Import the adapters' cards (torch-free): each declares its components in ``distilkit.registry`` (``ADAPTERS``,
    and LiDiff's task loss in ``TASK_LOSSES``), whose implementations are imported the first time they run."""
    from distilkit_adapters.dean import card as _dean  # noqa: F401
    from distilkit_adapters.js3cnet import card as _js3c  # noqa: F401
    from distilkit_adapters.lidiff import card as _lidiff  # noqa: F401
    from distilkit_adapters.scpnet import card as _scp  # noqa: F401
    from distilkit_adapters.voxformer import card as _voxformer  # noqa: F401
