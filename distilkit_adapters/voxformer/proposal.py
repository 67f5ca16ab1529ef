"""VoxFormer's stage 1: query proposals, occupancy at half resolution from predicted depth.

VoxFormer lifts a stereo depth network's depth to a pseudo point cloud and completes its occupancy with LMSCNet's
2-D U-Net over the bird's-eye plane (height as channels). Here one network does both: an image encoder with a depth
head (trained on the rendered depth), the current image's pixels lifted with the predicted depth (no gradient
through the lift, as VoxFormer's depth is fixed) and counted per voxel of the half-resolution grid, then a 2-D U-Net
over x, y with z as channels that gives empty / occupied scores per voxel.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from distilkit.structures import VoxelGrid
from distilkit_adapters.voxformer.backbone import ImageEncoder


def lift(depth: Tensor, intrinsics: Tensor, to_camera: Tensor) -> tuple[Tensor, Tensor]:
    """LiDAR-frame points (B, H*W, 3) of every pixel of (B, H, W) depth maps (pixel centres), and which are valid
    (depth > 0), for one camera per sample (``intrinsics`` (B, 3, 3), ``to_camera`` (B, 4, 4))."""
    b, h, w = depth.shape
    v, u = torch.meshgrid(torch.arange(h, device=depth.device, dtype=depth.dtype) + 0.5,
                          torch.arange(w, device=depth.device, dtype=depth.dtype) + 0.5, indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], -1).reshape(1, -1, 3)  # (1, HW, 3)
    rays = pix @ torch.linalg.inv(intrinsics).transpose(1, 2)  # (B, HW, 3), z = 1
    cam = rays * depth.reshape(b, -1, 1)
    to_lidar = torch.linalg.inv(to_camera)
    points = cam @ to_lidar[:, :3, :3].transpose(1, 2) + to_lidar[:, None, :3, 3]
    return points, depth.reshape(b, -1) > 0


def occupancy_counts(points: Tensor, valid: Tensor, grid: VoxelGrid) -> Tensor:
    """(B, Z, X, Y) log(1 + number of points) per voxel of ``grid``: the bird's-eye planes, height as channels."""
    b, n, _ = points.shape
    idx, inside = grid.index(points.reshape(-1, 3))
    keep = inside & valid.reshape(-1)
    x, y, z = grid.shape
    sample = torch.arange(b, device=points.device).repeat_interleave(n)
    flat = ((sample * z + idx[:, 2]) * x + idx[:, 0]) * y + idx[:, 1]
    counts = torch.zeros(b * z * x * y, device=points.device, dtype=points.dtype)
    counts.index_add_(0, flat[keep], torch.ones_like(flat[keep], dtype=points.dtype))
    return counts.view(b, z, x, y).log1p()


class BEVUNet(nn.Module):
    """LMSCNet-style 2-D U-Net over the bird's-eye plane: (B, Z, X, Y) in, (B, 2, X, Y, Z) empty/occupied out."""

    def __init__(self, height: int, width: int) -> None:
        super().__init__()

        def block(cin: int, cout: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1), nn.BatchNorm2d(cout), nn.ReLU(),
                                 nn.Conv2d(cout, cout, 3, 1, 1), nn.BatchNorm2d(cout), nn.ReLU())

        self.height = height
        self.enc1, self.enc2 = block(height, width), block(width, 2 * width)
        self.dec = block(3 * width, width)
        self.head = nn.Conv2d(width, 2 * height, 1)

    def forward(self, bev: Tensor) -> Tensor:
        e1 = self.enc1(bev)
        e2 = self.enc2(F.max_pool2d(e1, 2, ceil_mode=True))
        up = F.interpolate(e2, size=e1.shape[-2:], mode="bilinear", align_corners=False)
        out = self.head(self.dec(torch.cat([e1, up], 1)))  # (B, 2*Z, X, Y)
        b, _, x, y = out.shape
        return out.view(b, 2, self.height, x, y).permute(0, 1, 3, 4, 2).contiguous()


class QueryProposal(nn.Module):
    """Image -> depth (B, H, W) -> lifted, counted on the half-resolution grid -> occupancy scores (B, 2, X, Y, Z)."""

    def __init__(self, widths: list[int], channels: int, bev_width: int, grid: VoxelGrid, max_depth: float) -> None:
        super().__init__()
        self.encoder = ImageEncoder(widths, channels)
        self.depth_head = nn.Sequential(nn.Conv2d(channels, channels, 3, 1, 1), nn.ReLU(), nn.Conv2d(channels, 1, 1))
        self.grid = grid
        self.max_depth = max_depth
        self.bev = BEVUNet(grid.shape[2], bev_width)

    def forward(self, image: Tensor, intrinsics: Tensor, to_camera: Tensor) -> tuple[Tensor, Tensor]:
        """The current frame's ``image`` (B, 3, H, W) and calibration: (depth (B, H, W), scores (B, 2, X, Y, Z))."""
        feats = self.encoder(image)
        coarse = self.max_depth * torch.sigmoid(self.depth_head(feats))  # (B, 1, h, w) metres
        depth = F.interpolate(coarse, size=image.shape[-2:], mode="bilinear", align_corners=False)[:, 0]
        points, valid = lift(depth.detach(), intrinsics, to_camera)
        return depth, self.bev(occupancy_counts(points, valid, self.grid))


__all__ = ["BEVUNet", "QueryProposal", "lift", "occupancy_counts"]
