"""JS3C-Net at the paper's size as released (Yan et al., AAAI 2021; yanx27/JS3C-Net, the model of the release's
``log/JS3C-Net-kitti/args.txt``: ``SubSparseConv`` + ``SSCNet``), with its module names, so that its checkpoint
(a bare ``state_dict()`` of ``J3SC_Net``) loads key by key (``weights.from_release``):

* ``seg_head`` — ``sparseModel``: SparseConvNet (:mod:`.scn`) on voxels of ``seg_voxel`` (the release's
  ``scale: 20``: 0.05 m, the paper's resolution), every point of the scan, each voxel's mean intensity its one
  input feature (``InputLayer`` mode 4, ``use_coords: False``): ``1`` a 3^3 submanifold convolution 1 -> m,
  ``2`` ``scn.UNet`` over [m, 2m, ..., 7m] (m = 16, residual blocks, ``block_reps`` 1), ``3`` BN-ReLU; every point
  gets its voxel's features F (``OutputLayer``), the shape embedding F_SE = Conv1d-BN-LeakyReLU(0.2)(F)
  (``shape_embedding``) and the point logits ``linear(F + F_SE)`` over the K - 1 labelled classes (§3.1);
* voxel pooling (§3.2, ``VoxelPooling`` with ``pooling_type: mean``): each completion voxel's mean of [point logits,
  F_SE] (19 + 16 = 35 channels) over its first ``fuse_k`` = 5 points in scan order, a voxel with fewer padded with
  its first point (``index_feat``); the voxel is the one spconv's ``VoxelGenerator`` gives at the grid's 0.2 m, its
  z index raised by ``z_offset`` = 1 as ``train.py`` / ``test_kitti_ssc.py`` do ("SemanticKITTI will generate
  [256,256,31]"; a voxel raised past the grid is dropped);
* ``complet_head.Decoder`` — ``SSCNet_Decoder`` as released (dense): ``b1_conv1`` 7^3 stride 2 -> 16, residual
  blocks 1-2, blocks 3-5 (4-5 dilated by 2) summed pairwise, their concatenation -> ``pre_conv1`` (2/3 of it) ->
  ``pre_conv2`` (K classes) at half resolution;
* ``complet_head.interaction_module`` — the point-voxel interaction (§3.3): supports are the pooled voxels (their
  detached F_SE at the voxel centres), queries the non-zero coarse voxels (``pvi_queries: all``); for each query
  its ``k`` nearest supports give [offset, centre, support xyz, distance] -> ``relation_w`` (Conv1d-BN-LeakyReLU(0.2),
  10 -> m), which multiplies the support features, mean over k; ``fuse_mlps`` (FC-BN-LeakyReLU(0.2)) on [that, coarse
  logits] replaces the coarse logits at the queries (0 elsewhere, as ``feat.dense()`` leaves them);
* ``complet_head.upsample`` — 1^3 convolution to 8K channels, BN, ReLU (the logits are >= 0, as released), 3-D
  pixel shuffle -> logits on the full grid.

Where this differs from the release, by choice (also in the adapter's ``CHOICES``): the segmentation voxels are the
scan's own (the release rotates, scales and shifts the scan at random at every call, test time included:
``kitti_dataset.process_seg_data``), aligned so that the six 2^3 poolings floor as on the metric grid; the k
nearest supports are exact with ties (equidistant voxel centres) broken by the lower voxel index (the release's
nanoflann breaks them by its tree's order); with a batch of several scans each voxel is padded with its own first
point (the release pads with the batch's first point, ``Merge`` offsets its zero padding; it trains with batch 1).
``pvi_queries: near`` queries only the coarse voxels occupied or next to one and fuses every coarse voxel (faster,
not the release).
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Literal

import torch
from torch import Tensor, nn

from distilkit.geometry.knn import grid_knn as exact_grid_knn
from distilkit.sparse import SparseConvTensor, name_modules
from distilkit.sparse.points import voxelize_flat
from distilkit.structures import VoxelGrid
from distilkit_adapters.js3cnet import scn
from distilkit_adapters.js3cnet.model import near_queries, pixel_shuffle_3d, relation


class ConvBNAct(nn.Sequential):
    """The release's ``conv_base.Conv1d`` / ``FC`` with ``bn=True``: ``conv`` or ``fc`` (no bias), ``bn.bn``,
    ``activation``."""

    def __init__(self, cin: int, cout: int, linear: bool) -> None:
        super().__init__()
        self.add_module("fc" if linear else "conv", nn.Linear(cin, cout, bias=False) if linear
                        else nn.Conv1d(cin, cout, 1, bias=False))
        self.add_module("bn", nn.Sequential(OrderedDict(bn=nn.BatchNorm1d(cout))))
        self.add_module("activation", nn.LeakyReLU(0.2))


class SegHead(nn.Module):
    """``SubSparseConv.Unet``: ``sparseModel`` (SparseConvNet), ``linear``, ``shape_embedding``."""

    def __init__(self, m: int, levels: int, seg_classes: int) -> None:
        super().__init__()
        self.sparseModel = (scn.Sequential().add(scn.InputLayer()).add(scn.SubmanifoldConvolution(1, m, 0))
                            .add(scn.unet(1, [m * (i + 1) for i in range(levels)], residual=True))
                            .add(scn.BatchNormReLU(m)).add(scn.OutputLayer()))
        self.linear = nn.Linear(m, seg_classes)
        self.shape_embedding = ConvBNAct(m, m, linear=False)

    def forward(self, x: SparseConvTensor, point_rows: Tensor) -> tuple[Tensor, Tensor]:
        """Point logits and F_SE (P, m) of the points whose voxel rows are ``point_rows``."""
        feats = self.sparseModel(x).features[point_rows]
        embed = self.shape_embedding(feats.t()[None])[0].t()
        return self.linear(feats + embed), embed


def _c3(cin: int, cout: int, k: int = 3, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, k, stride, padding=dilation * (k // 2), dilation=dilation),
                         nn.BatchNorm3d(cout), nn.ReLU())


class SSCNetDecoder(nn.Module):
    """``SSCNet_Decoder`` with five widths ``m`` (the release: 32)."""

    def __init__(self, cin: int, m: int, num_classes: int) -> None:
        super().__init__()
        self.b1_conv1, self.b1_conv2, self.b1_conv3 = _c3(cin, 16, 7, 2), _c3(16, m), _c3(m, m)
        self.b1_res = _c3(16, m)
        self.b2_conv1, self.b2_conv2, self.b2_res = _c3(m, m), _c3(m, m), _c3(m, m)
        self.b3_conv1, self.b3_conv2 = _c3(m, m), _c3(m, m)
        self.b4_conv1, self.b4_conv2 = _c3(m, m, dilation=2), _c3(m, m, dilation=2)
        self.b5_conv1, self.b5_conv2 = _c3(m, m, dilation=2), _c3(m, m, dilation=2)
        fused = int(3 * m / 3 * 2)
        self.pre_conv1 = nn.Sequential(nn.Conv3d(3 * m, fused, 1), nn.BatchNorm3d(fused), nn.ReLU())
        self.pre_conv2 = nn.Sequential(nn.Conv3d(fused, num_classes, 1))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """(features after ``pre_conv1``, coarse logits), both at half resolution."""
        x = self.b1_conv1(x)
        x = self.b1_conv3(self.b1_conv2(x)) + self.b1_res(x)
        x = self.b2_conv2(self.b2_conv1(x)) + self.b2_res(x)
        outs = []
        for first, second in ((self.b3_conv1, self.b3_conv2), (self.b4_conv1, self.b4_conv2),
                              (self.b5_conv1, self.b5_conv2)):
            a = first(x)
            x = a + second(a)
            outs.append(x)
        feat = self.pre_conv1(torch.cat(outs, 1))
        return feat, self.pre_conv2(feat)


class Interaction(nn.Module):
    """The point-voxel interaction (``interaction_module``, relation features without the support features)."""

    def __init__(self, m: int, num_classes: int, k: int) -> None:
        super().__init__()
        self.k = k
        self.relation_w = ConvBNAct(10, m, linear=False)
        self.fuse_mlps = ConvBNAct(m + num_classes, num_classes, linear=True)

    def aggregate(self, q_xyz: Tensor, s_xyz: Tensor, s_feat: Tensor, idx: Tensor) -> Tensor:
        """(Q, m): the relation-weighted mean of the features of each query's supports ``idx`` (Q, k)."""
        if q_xyz.shape[0] == 0 or s_xyz.shape[0] == 0:
            return s_feat.new_zeros(q_xyz.shape[0], s_feat.shape[1])
        w = self.relation_w(relation(q_xyz, s_xyz, idx).permute(0, 2, 1))  # (Q, m, k)
        return (w * s_feat[idx].permute(0, 2, 1)).mean(2)


class CompletHead(nn.Module):
    def __init__(self, cin: int, m_seg: int, m: int, num_classes: int, k: int) -> None:
        super().__init__()
        self.Decoder = SSCNetDecoder(cin, m, num_classes)
        self.interaction_module = Interaction(m_seg, num_classes, k)
        self.upsample = nn.Sequential(nn.Conv3d(num_classes, num_classes * 8, 1), nn.BatchNorm3d(num_classes * 8),
                                      nn.ReLU())  # then the pixel shuffle


def first_k_mean(values: Tensor, groups: Tensor, n_groups: int, k: int) -> Tensor:
    """(G, C): per group, the mean over k slots of ``values`` of its first ``k`` rows in input order, a group with
    fewer rows filling the rest with its first row (the release's ``VoxelPooling.index_feat``); 0 for an empty
    group (groups (P,) in [0, G))."""
    order = torch.sort(groups, stable=True).indices
    sorted_groups = groups[order]
    starts = torch.searchsorted(sorted_groups, sorted_groups, right=False)
    rank = torch.arange(len(order), device=groups.device) - starts
    chosen = order[rank < k]
    g = groups[chosen]
    total = values.new_zeros(n_groups, values.shape[1]).index_add_(0, g, values[chosen])
    count = torch.bincount(g, minlength=n_groups)
    first = values.new_zeros(n_groups, values.shape[1]).index_copy_(0, groups[order[rank == 0]],
                                                                     values[order[rank == 0]])
    return (total + (k - count).clamp_min(0).to(values.dtype)[:, None] * first) / k * (count > 0)[:, None]


def grid_knn(query: Tensor, support: Tensor, k: int) -> Tensor:
    """(Q, min(k, S)) indices of each query's k nearest supports, both given as (Q, 3) / (S, 3) int64 coordinates
    in one unit (distances exact), ties broken by the lower support index: ``distilkit.geometry.knn.grid_knn``, on
    the points' device."""
    return exact_grid_knn(query, support, k)


def _centres(coords: Tensor, grid: VoxelGrid, stride: int, dtype: torch.dtype) -> Tensor:
    """(N, 3) centres of (N, 4) voxel indices at ``stride`` times the grid's voxel, in ``dtype`` (the release's
    ``align_pnt``: (index + 0.5) voxel + the range's minimum)."""
    origin = torch.tensor(grid.origin, dtype=dtype, device=coords.device)
    return (coords[:, 1:].to(dtype) + 0.5) * (grid.voxel_size * stride) + origin


class JS3CNetPaper(nn.Module):
    def __init__(self, num_classes: int, m: int = 16, levels: int = 7, ssc_m: int = 32, k: int = 8,
                 fuse_k: int = 5, pvi_queries: Literal["all", "near"] = "all", seg_voxel: float = 0.05,
                 z_offset: int = 1) -> None:
        super().__init__()
        self.k_classes, self.levels, self.fuse_k, self.pvi_queries = num_classes, levels, fuse_k, pvi_queries
        self.seg_voxel, self.z_offset = seg_voxel, z_offset
        self.seg_head = SegHead(m, levels, num_classes - 1)
        self.complet_head = CompletHead(num_classes - 1 + m, m, ssc_m, num_classes, k)
        name_modules(self)

    def pool(self, points: Tensor, point_batch: Tensor, batch_size: int, grid: VoxelGrid,
             features: Tensor) -> tuple[Tensor, Tensor]:
        """(the flat (B, X, Y, Z) indices of the completion voxels with points, raised by ``z_offset``; their pooled
        ``features``)."""
        idx, inside = grid.index(points[:, :3])
        z = idx[:, 2] + self.z_offset
        inside = inside & (z < grid.shape[2])
        x, y, zs = grid.shape
        flat = ((point_batch[inside].long() * x + idx[inside, 0]) * y + idx[inside, 1]) * zs + z[inside]
        uniq, rows = torch.unique(flat, return_inverse=True)
        return uniq, first_k_mean(features[inside], rows, len(uniq), self.fuse_k)

    def forward(self, points: Tensor, point_batch: Tensor, batch_size: int, grid: VoxelGrid) -> dict[str, Tensor]:
        # segmentation on its own fine grid, every point of the scan
        seg = voxelize_flat(points[:, :3], point_batch, batch_size, self.seg_voxel, 2 ** (self.levels - 1),
                            points[:, 3:4], rounding="floor")
        point_logits, f_se = self.seg_head(seg.tensor, seg.point_rows)
        uniq, pooled = self.pool(points, point_batch, batch_size, grid, torch.cat([point_logits, f_se], 1))
        x, y, z = grid.shape
        dense = pooled.new_zeros(batch_size * x * y * z, pooled.shape[1])
        dense[uniq] = pooled
        feat, coarse = self.complet_head.Decoder(dense.view(batch_size, x, y, z, -1).permute(0, 4, 1, 2, 3))
        # the point-voxel interaction: supports at the pooled voxels' centres, queries at the coarse voxels'
        s_feat = pooled[:, self.k_classes - 1:].detach()
        s_coords = torch.stack(torch.unravel_index(uniq, (batch_size, x, y, z)), 1)
        keep = s_feat.abs().sum(1) > 0  # the non-zero voxels of the support tensor
        s_coords, s_feat = s_coords[keep], s_feat[keep]
        logits_cl = coarse.permute(0, 2, 3, 4, 1)  # (B, X/2, Y/2, Z/2, K)
        query = logits_cl.detach().abs().sum(-1) > 0
        if self.pvi_queries == "near":
            query = near_queries(uniq, batch_size, grid.shape)
        qc = query.nonzero()
        s_xyz, q_xyz = _centres(s_coords, grid, 1, pooled.dtype), _centres(qc, grid, 2, pooled.dtype)
        pvi = self.complet_head.interaction_module
        parts = []
        for b in range(batch_size):
            qb, sb = qc[:, 0] == b, s_coords[:, 0] == b
            idx = grid_knn(4 * qc[qb, 1:] + 2, 2 * s_coords[sb, 1:] + 1, pvi.k)  # in units of half a voxel
            parts.append(pvi.aggregate(q_xyz[qb], s_xyz[sb], s_feat[sb], idx))
        agg_q = torch.cat(parts)
        if self.pvi_queries == "all":  # fused at the queries, 0 elsewhere (the release's feat.dense())
            fused = logits_cl.new_zeros(logits_cl.shape)
            fused[query] = pvi.fuse_mlps(torch.cat([agg_q, logits_cl[query]], -1))
        else:  # every coarse voxel fused, the ones without a query with nothing aggregated
            agg = logits_cl.new_zeros(*logits_cl.shape[:-1], agg_q.shape[1])
            agg[query] = agg_q
            fused = pvi.fuse_mlps(torch.cat([agg, logits_cl], -1).reshape(-1, agg.shape[-1] + self.k_classes))
            fused = fused.view(logits_cl.shape)
        logits = pixel_shuffle_3d(self.complet_head.upsample(fused.permute(0, 4, 1, 2, 3)), 2)
        return {"logits": logits, "point_logits": point_logits, "ssc_coords": qc,
                "ssc_feats": feat.permute(0, 2, 3, 4, 1)[query], "ssc_dense": feat}
