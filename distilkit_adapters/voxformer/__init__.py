"""VoxFormer-style camera models (stage 1 query proposals, stage 2 voxel queries)."""
