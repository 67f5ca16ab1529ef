"""distilkit's built-in adapters (installed as ``distilkit_adapters``), loaded through the
``distilkit.plugins`` entry point like any third-party plugin."""


def register() -> None:
    """Import the adapter modules; each registers itself in ``distilkit.registry.ADAPTERS``."""
    from distilkit_adapters.dean import adapter as _dean  # noqa: F401
    from distilkit_adapters.js3cnet import adapter as _js3c  # noqa: F401
    from distilkit_adapters.lidiff import adapter as _lidiff  # noqa: F401
    from distilkit_adapters.lidiff import loss as _lidiff_loss  # noqa: F401
    from distilkit_adapters.lidiff import refine as _lidiff_refine  # noqa: F401
    from distilkit_adapters.scpnet import adapter as _scp  # noqa: F401
    from distilkit_adapters.voxformer import adapter as _voxformer  # noqa: F401
