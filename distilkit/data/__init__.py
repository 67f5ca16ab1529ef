"""Data: synthetic LiDAR scenes, SemanticKITTI IO, datasets and collation."""
