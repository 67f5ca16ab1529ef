"""Engine: recipe resolution, the trainer, the pipeline of stages, checkpoints and reports."""
