"""SCPNet (Xia et al., CVPR 2023): completion sub-network of Multi-Path Blocks + segmentation sub-network."""
