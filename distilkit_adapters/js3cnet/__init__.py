"""JS3C-Net (Yan et al., AAAI 2021): segmentation branch, SSC module, point-voxel interaction."""
