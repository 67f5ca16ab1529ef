"""What is done with a finished run: ``distilkit predict`` (a SemanticKITTI folder's frames in the submission
format), ``distilkit complete`` (a scan completed into a dense scene) and ``distilkit export`` (a student's weights
alone). Uses :mod:`~distilkit.engine.assemble` and :mod:`~distilkit.engine.store`; nothing that trains."""
