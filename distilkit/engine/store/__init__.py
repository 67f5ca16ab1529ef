"""What a run leaves on disk and how it is named: a stage's checkpoints (``last.pt``, ``best.pt``), the lock that
gives a stage one writer, the identity that names its folder, the predictions it publishes for later stages. Uses
the library's lower layers only (files, errors, the registries); nothing of the engine."""
