"""VoxFormer's stage 2 as released (Li et al. CVPR 2023; NVlabs/VoxFormer ``VoxFormer`` detector with
``VoxFormerHead``, configs ``voxformer-S.py`` / ``-T.py`` and their ``_deform3D`` twins), under the checkpoint's
module names (``img_backbone``, ``img_neck``, ``pts_bbox_head``) so that a released checkpoint loads
(:mod:`.weights`). Written from the release's facts:

* ``img_backbone`` — ResNet-50 to its third stage (torchvision's names, frozen batch norms and first stage), images
  normalised with ImageNet's statistics as the release's loader does; ``img_neck`` — a one-level FPN to C = 128;
* ``pts_bbox_head``: ``bev_embed`` (one learned query per voxel of the X x Y x Z query grid, 128 x 128 x 16 at
  SemanticKITTI's size), ``mask_embed``, ``positional_encoding`` (:class:`~.transformer.LearnedPositionalEncoding`),
  ``cross_transformer`` (3 layers of :class:`~.deformable.DeformCrossAttention` + FFN: only the proposed queries,
  each reading the images around its voxel centre's projection: the release's ``point_sampling``, depth > 1e-5 and
  strictly inside the image), ``self_transformer`` (2 layers of :class:`~.deformable.DeformSelfAttention` + FFN over
  every query, the proposed ones with their cross-attention features and the others with ``mask_embed``), and
  ``header``: trilinear x2 upsampling with ``align_corners=True`` (``nn.Upsample`` in ``utils/header.py``), then
  ``mlp_head`` = LayerNorm + Linear to the classes.

A batch is handled sample by sample (the release runs one sample and reads the proposals of the first).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from distilkit.structures import SparseVoxels, VoxelGrid
from distilkit_adapters.voxformer.attention import DEPTH_EPS
from distilkit_adapters.voxformer.deformable import plane_shape
from distilkit_adapters.voxformer.resnet import FPN, IMAGENET_MEAN, IMAGENET_STD, ResNet50
from distilkit_adapters.voxformer.transformer import (LearnedPositionalEncoding, PerceptionTransformer, cross_layer,
                                                      self_layer)


class Header(nn.Module):
    def __init__(self, embed_dims: int, num_classes: int) -> None:
        super().__init__()
        self.mlp_head = nn.Sequential(nn.LayerNorm(embed_dims), nn.Linear(embed_dims, num_classes))

    def forward(self, volume: Tensor) -> Tensor:
        """(B, C, X, Y, Z) -> (B, K, 2X, 2Y, 2Z)."""
        up = F.interpolate(volume, scale_factor=2, mode="trilinear", align_corners=True)
        return self.mlp_head(up.permute(0, 2, 3, 4, 1)).permute(0, 4, 1, 2, 3)


class VoxFormerHead(nn.Module):
    def __init__(self, query_grid: VoxelGrid, embed_dims: int, heads: int, points: int, cross_layers: int,
                 self_layers: int, frames: int, num_classes: int, space: str) -> None:
        super().__init__()
        self.query_grid = query_grid
        n = query_grid.shape[0] * query_grid.shape[1] * query_grid.shape[2]
        ffn = 2 * embed_dims
        self.bev_embed = nn.Embedding(n, embed_dims)
        self.mask_embed = nn.Embedding(1, embed_dims)
        self.positional_encoding = LearnedPositionalEncoding(embed_dims // 2)
        self.cross_transformer = PerceptionTransformer(
            [cross_layer(embed_dims, heads, points, ffn) for _ in range(cross_layers)], embed_dims, frames)
        self.self_transformer = nn.Module()  # the release's also has embeddings of images it never reads
        self.self_transformer.encoder = nn.Module()
        self.self_transformer.encoder.layers = nn.ModuleList(
            self_layer(embed_dims, heads, points, ffn, space) for _ in range(self_layers))
        self.header = Header(embed_dims, num_classes)

    def references(self, lidar_to_image: Tensor, image_size: tuple[int, int]) -> tuple[Tensor, Tensor]:
        """The voxel centres' projections (T, N, 2) in 0..1 of the image and whether each is seen (T, N): the
        release's ``point_sampling`` (centres in float64, projected in float32 — or the calibration's precision if
        higher —, depth clamped to 1e-5, strictly inside)."""
        g = self.query_grid
        f64 = dict(dtype=torch.float64, device=lidar_to_image.device)
        idx = torch.stack(torch.meshgrid(*(torch.arange(s, device=lidar_to_image.device) for s in g.shape),
                                         indexing="ij"), -1).view(-1, 3)
        shape = torch.tensor(g.shape, **f64)
        ref = (idx.double() + 0.5) / shape
        centres = ref * (shape * g.voxel_size) + torch.tensor(g.origin, **f64)  # metres: ref x range + min
        dtype = torch.promote_types(torch.float32, lidar_to_image.dtype)
        points = torch.cat([centres, torch.ones_like(centres[:, :1])], 1).to(dtype)
        cam = torch.einsum("tij,nj->tni", lidar_to_image.to(dtype), points)
        depth = cam[..., 2:3]
        uv = cam[..., :2] / depth.clamp_min(DEPTH_EPS) / cam.new_tensor([image_size[1], image_size[0]])
        seen = (depth[..., 0] > DEPTH_EPS) & (uv > 0).all(-1) & (uv < 1).all(-1)
        return uv, seen

    def forward(self, values: Tensor, shape: tuple[int, int], uv: Tensor, seen: Tensor,
                proposed: Tensor) -> tuple[Tensor, Tensor]:
        """One sample: image ``values`` (T, h * w, C) on ``shape``, projections (T, N, 2) and ``seen`` (T, N),
        ``proposed`` (N,) bool -> (the proposed queries after cross-attention (P, C), the query volume after
        self-attention (N, C))."""
        rows = proposed.nonzero().squeeze(1)
        x = self.bev_embed.weight[rows]
        ref, sees = uv[:, rows].to(x.dtype), seen[:, rows]
        for layer in self.cross_transformer.encoder.layers:
            x = layer.finish(layer.attentions[0](x, values, ref, sees, shape))
        volume = self.mask_embed.weight.repeat(len(proposed), 1).index_put((rows,), x)
        pos = self.positional_encoding(len(proposed), *plane_shape(len(proposed)))
        for layer in self.self_transformer.encoder.layers:
            volume = layer.finish(layer.attentions[0](volume[None], pos, self.query_grid.shape)[0])
        return x, volume


class VoxFormerRelease(nn.Module):
    """``VoxFormer`` (stage 2): images, calibration and proposals -> image features, proposed queries, logits."""

    def __init__(self, grid: VoxelGrid, num_classes: int, embed_dims: int = 128, heads: int = 8, points: int = 8,
                 cross_layers: int = 3, self_layers: int = 2, frames: int = 1, space: str = "plane") -> None:
        super().__init__()
        self.grid, self.query_grid = grid, grid.coarsen(2)
        self.img_backbone = ResNet50()
        self.img_neck = FPN(self.img_backbone.out_channels, embed_dims)
        self.pts_bbox_head = VoxFormerHead(self.query_grid, embed_dims, heads, points, cross_layers, self_layers,
                                           frames, num_classes, space)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, images: Tensor, intrinsics: Tensor, to_camera: Tensor,
                occupied: Tensor) -> tuple[Tensor, SparseVoxels, Tensor]:
        """``images`` (B, T, 3, H, W) in 0..1, ``intrinsics`` (B, T, 3, 3), ``to_camera`` (B, T, 4, 4), ``occupied``
        (B, X/2, Y/2, Z/2) proposals -> (image features (B, T, C, h, w), the proposed queries after cross-attention
        (sparse voxels on the query grid), logits (B, K, X, Y, Z))."""
        b, t = images.shape[:2]
        feats = self.img_neck(self.img_backbone((images.flatten(0, 1) - self.mean) / self.std))
        feats = feats.view(b, t, *feats.shape[1:])
        pad = torch.zeros(b, t, 4, 4, dtype=intrinsics.dtype, device=intrinsics.device)
        pad[..., :3, :3] = intrinsics
        pad[..., 3, 3] = 1
        lidar_to_image = pad @ to_camera  # the release's lidar2img = viewpad @ lidar2cam
        head = self.pts_bbox_head
        coords, queries, volumes = [], [], []
        for i in range(b):
            values = head.cross_transformer.embed(feats[i])
            uv, seen = head.references(lidar_to_image[i], tuple(images.shape[-2:]))
            proposed = occupied[i].reshape(-1)
            q, volume = head(values, tuple(feats.shape[-2:]), uv, seen, proposed)
            flat = proposed.nonzero().squeeze(1)
            coords.append(torch.cat([torch.full_like(flat[:, None], i),
                                     torch.stack(torch.unravel_index(flat, self.query_grid.shape), 1)], 1))
            queries.append(q)
            volumes.append(volume.T.reshape(-1, *self.query_grid.shape))
        logits = head.header(torch.stack(volumes))
        return feats, SparseVoxels(torch.cat(coords), torch.cat(queries), self.query_grid.shape, self.query_grid), \
            logits


__all__ = ["Header", "VoxFormerHead", "VoxFormerRelease"]
