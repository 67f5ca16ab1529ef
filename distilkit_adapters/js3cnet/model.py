"""JS3C-Net's network (Yan et al., AAAI 2021, §3 and Fig. 2-3), sized for CPU runs.

* Segmentation branch: point encoder, voxel U-Net (the paper's SparseConv U-Net; here the dense
  :class:`DenseUNet3d` on the SSC grid), features brought back to the points by their voxel
  (nearest-neighbour interpolation), shape embedding F_SE = MLP_1(F_enc), and
  F_out = MLP_3(MLP_2(F_enc) + F_SE) -> point logits.
* SSC module: voxel pooling of [point logits, F_SE] (mean per voxel), then a dense decoder: a
  7x7x7 stride-2 convolution to half resolution, three residual blocks (the last two dilated by
  2), their concatenation fused by 1x1x1 convolutions -> coarse completion logits.
* Point-voxel interaction (PVI): query = coarse voxels near the input (occupied children,
  dilated by one voxel); support = occupied fine voxels carrying F_SE at their centres; for
  each query its k nearest supports give relation features [offset, centre, support xyz,
  distance] -> MLP weights that modulate the support features; the mean over k, concatenated
  with the coarse logits, refines them residually (FC). 
* Up-sampling: 1x1x1 convolution to 8K channels and a 3-D pixel shuffle (factor 2) -> logits on
  the full grid. The authors' final ReLU on the logits (seed_code.md §4) is left out.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from distilkit.geometry.knn import knn
from distilkit.structures import VoxelGrid
from distilkit_adapters._blocks import DenseUNet3d, conv_bn, point_features, point_voxel_index


def mlp(dims: list[int]) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        layers += [nn.Linear(a, b), nn.BatchNorm1d(b), nn.LeakyReLU(0.1, inplace=True)]
    return nn.Sequential(*layers)


def pixel_shuffle_3d(x: Tensor, r: int) -> Tensor:
    """(B, C*r^3, X, Y, Z) -> (B, C, X*r, Y*r, Z*r)."""
    b, c, x_, y_, z_ = x.shape
    c_out = c // (r ** 3)
    x = x.view(b, c_out, r, r, r, x_, y_, z_).permute(0, 1, 5, 2, 6, 3, 7, 4)
    return x.reshape(b, c_out, x_ * r, y_ * r, z_ * r)


def relation(q_xyz: Tensor, s_xyz: Tensor, idx: Tensor) -> Tensor:
    """The PVI's relation of each query to its supports ``idx`` (Q, k): (Q, k, 10) [offset, centre, support xyz,
    distance] (the release's ``VoxelPooling.relation_position``)."""
    nb = s_xyz[idx]  # (Q, k, 3)
    offset = nb - q_xyz[:, None]
    return torch.cat([offset, q_xyz[:, None].expand_as(nb), nb, offset.norm(dim=-1, keepdim=True)], dim=-1)


def relation_features(q_xyz: Tensor, s_xyz: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """:func:`relation` to each query's k nearest supports and their indices (Q, k)."""
    dist, idx = knn(q_xyz, s_xyz, k)
    nb = s_xyz[idx]  # (Q, k, 3)
    return torch.cat([nb - q_xyz[:, None], q_xyz[:, None].expand_as(nb), nb, dist[..., None]], dim=-1), idx


def near_queries(occupied: Tensor, batch_size: int, shape: tuple[int, int, int]) -> Tensor:
    """(B, X/2, Y/2, Z/2) bool: the coarse voxels with an occupied child or next to one, from the occupied voxels'
    flat indices over (B, X, Y, Z)."""
    occ = torch.zeros(batch_size * shape[0] * shape[1] * shape[2], device=occupied.device)
    occ[occupied] = 1.0
    coarse = F.max_pool3d(occ.view(batch_size, 1, *shape), 2)
    return F.max_pool3d(coarse, 3, stride=1, padding=1)[:, 0] > 0


class ResBlock(nn.Module):
    def __init__(self, c: int, dilation: int = 1) -> None:
        super().__init__()
        self.body = nn.Sequential(conv_bn(c, c, 3, dilation=dilation),
                                  nn.Conv3d(c, c, 3, padding=dilation, dilation=dilation, bias=False), nn.BatchNorm3d(c))

    def forward(self, x: Tensor) -> Tensor:
        return F.leaky_relu(x + self.body(x), 0.1)


class SSCDecoder(nn.Module):
    def __init__(self, cin: int, c: int, num_classes: int) -> None:
        super().__init__()
        self.stem = conv_bn(cin, c, 7, stride=2)
        self.blocks = nn.ModuleList([ResBlock(c), ResBlock(c, 2), ResBlock(c, 2)])
        self.fuse = nn.Sequential(nn.Conv3d(3 * c, 2 * c, 1), nn.LeakyReLU(0.1, inplace=True))
        self.cls = nn.Conv3d(2 * c, num_classes, 1)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        h = self.stem(x)
        outs = []
        for blk in self.blocks:
            h = blk(h)
            outs.append(h)
        feat = self.fuse(torch.cat(outs, 1))
        return feat, self.cls(feat)


class PointVoxelInteraction(nn.Module):
    def __init__(self, embed: int, hidden: int, num_classes: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.weight_net = nn.Sequential(nn.Linear(10, hidden), nn.BatchNorm1d(hidden), nn.LeakyReLU(0.2),
                                        nn.Linear(hidden, hidden))
        self.value = nn.Linear(embed, hidden)
        self.refine = nn.Linear(hidden + num_classes, num_classes)

    def forward(self, q_xyz: Tensor, q_logits: Tensor, s_xyz: Tensor, s_feat: Tensor) -> Tensor:
        if s_xyz.shape[0] == 0 or q_xyz.shape[0] == 0:
            return q_logits
        rel, idx = relation_features(q_xyz, s_xyz, self.k)
        w = self.weight_net(rel.reshape(-1, 10)).view(*idx.shape, -1)
        agg = (w * self.value(s_feat)[idx]).mean(1)
        return q_logits + self.refine(torch.cat([agg, q_logits], 1))


class JS3CNet(nn.Module):
    def __init__(self, grid: VoxelGrid, num_classes: int, seg_channels: int, embed: int, ssc_channels: int,
                 pvi_hidden: int, k: int) -> None:
        super().__init__()
        self.grid, self.k_classes = grid, num_classes
        self.encoder = mlp([7, 32, seg_channels])
        self.unet = DenseUNet3d(seg_channels, seg_channels, seg_channels)
        self.mlp1 = mlp([seg_channels, embed])
        self.mlp2 = mlp([seg_channels, embed])
        self.mlp3 = nn.Sequential(mlp([embed, embed]), nn.Linear(embed, num_classes))
        self.ssc = SSCDecoder(num_classes + embed, ssc_channels, num_classes)
        self.pvi = PointVoxelInteraction(embed, pvi_hidden, num_classes, k)
        self.up = nn.Conv3d(num_classes, num_classes * 8, 1)

    def forward(self, batch: dict[str, Tensor], batch_size: int) -> dict[str, Tensor]:
        grid = self.grid
        keep, idx, flat = point_voxel_index(batch, grid)
        pts, idx, flat = batch["points"][keep], idx[keep], flat[keep]
        x, y, z = grid.shape
        n_vox = batch_size * x * y * z
        # segmentation branch
        enc = self.encoder(point_features(pts, idx, grid))
        uniq, inv = torch.unique(flat, return_inverse=True)
        counts = torch.zeros(uniq.numel(), device=pts.device).index_add_(0, inv, torch.ones_like(inv, dtype=torch.float))
        # summed in float32 whatever autocast gave the encoder (an index_add_ of half values into float32 stops)
        pooled = torch.zeros(uniq.numel(), enc.shape[1], device=pts.device).index_add_(0, inv, enc.float()) / counts[:, None]
        dense = pooled.new_zeros(n_vox, enc.shape[1])
        dense[uniq] = pooled
        vol = self.unet(dense.view(batch_size, x, y, z, -1).permute(0, 4, 1, 2, 3))
        f_enc = vol.permute(0, 2, 3, 4, 1).reshape(n_vox, -1)[flat]
        f_se = self.mlp1(f_enc)
        point_logits = self.mlp3(self.mlp2(f_enc) + f_se)
        # SSC module on voxel-pooled [logits, F_SE]
        both = torch.cat([point_logits, f_se], 1)
        vpool = both.new_zeros(uniq.numel(), both.shape[1]).index_add_(0, inv, both) / counts[:, None]
        ssc_in = vpool.new_zeros(n_vox, both.shape[1])
        ssc_in[uniq] = vpool
        feat, coarse = self.ssc(ssc_in.view(batch_size, x, y, z, -1).permute(0, 4, 1, 2, 3))
        # PVI on coarse voxels near the input
        query = near_queries(uniq, batch_size, grid.shape)
        qc = query.nonzero()  # (Q,4)
        cgrid = grid.coarsen(2)
        q_xyz = cgrid.centers(qc[:, 1:])
        q_logits = coarse.permute(0, 2, 3, 4, 1)[query]
        s_coords = torch.stack(torch.unravel_index(uniq, (batch_size, x, y, z)), 1)
        s_xyz = grid.centers(s_coords[:, 1:])
        s_feat = vpool[:, self.k_classes:]
        refined = torch.empty_like(q_logits)
        for b in range(batch_size):
            qm, sm = qc[:, 0] == b, s_coords[:, 0] == b
            refined[qm] = self.pvi(q_xyz[qm], q_logits[qm], s_xyz[sm], s_feat[sm])
        coarse_ref = coarse.permute(0, 2, 3, 4, 1).clone()
        coarse_ref[query] = refined
        coarse_ref = coarse_ref.permute(0, 4, 1, 2, 3)
        logits = pixel_shuffle_3d(self.up(coarse_ref), 2)
        return {"logits": logits, "point_logits": point_logits, "point_keep": keep,
                "ssc_coords": qc, "ssc_feats": feat.permute(0, 2, 3, 4, 1)[query], "ssc_dense": feat}
