"""Scribble2Scene's Dean-Labeler: voxel segmentation of the complete geometry, trained on scribbles."""
