"""LiDiff: a diffusion model that completes a LiDAR scan into a dense scene (Nunes et al., CVPR 2024)."""
