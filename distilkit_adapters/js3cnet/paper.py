"""JS3C-Net at the paper's size (Yan et al., AAAI 2021; yanx27/JS3C-Net), with the release's module names
(``seg_head.*``, ``complet_head.*``) so that its state dicts line up key by key:

* ``seg_head`` — the segmentation branch on a grid half the completion voxel (0.1 m at 0.2 m, the release's
  ``scale: 10``), every point of the scan, the mean intensity per voxel as the one input feature
  (``use_coords: False``): ``input_conv`` (3^3 submanifold, 1 -> m), ``backbone_net`` — the U-Net of the release's
  spconv port (``UBlock``: ``blocks`` of BN-ReLU-SubM 3^3, ``conv`` BN-ReLU-2^3 stride-2 ``SparseConv3d``, ``u``
  the next level, ``deconv`` BN-ReLU-``SparseInverseConv3d``, ``blocks_tail`` on the concatenated skip) over
  ``[m, 2m, ..., 7m]`` (the reported ``JS3C_default_kitti.yaml``: m = 16, seven levels, one VGG block each), then
  ``output_layer`` (BN-ReLU); per point: its voxel's features F, the shape embedding F_SE = Conv1d-BN-LeakyReLU(0.2)
  (F) and the point logits ``linear(F + F_SE)`` (§3.1);
* voxel pooling (§3.2): each completion voxel's mean of [point logits of the K-1 labelled classes, F_SE] over its
  first ``fuse_k`` points (the release's 19 + 16 = 35 channels);
* ``complet_head.Decoder`` — ``SSCNet_Decoder`` as released (dense): ``b1_conv1`` 7^3 stride 2 -> 16, residual
  blocks 1-2, blocks 3-5 (4-5 dilated by 2) summed pairwise, their concatenation -> ``pre_conv1`` (2/3 of it) ->
  ``pre_conv2`` (K classes) at half resolution;
* ``complet_head.interaction_module`` — the point-voxel interaction (§3.3): supports are the completion voxels with
  points (their detached F_SE at the voxel centres), queries the coarse voxels; for each query its ``k`` nearest
  supports give [offset, centre, support xyz, distance] -> ``relation_w`` (Conv1d-BN-LeakyReLU(0.2), 10 -> m),
  which multiplies the support features, mean over k; ``fuse_mlps`` (FC-BN-LeakyReLU(0.2)) on [that, coarse logits]
  replaces the coarse logits;
* ``complet_head.upsample`` — 1^3 convolution to 8K channels, BN, 3-D pixel shuffle -> logits on the full grid.

Choices against the release (also in the adapter's ``CHOICES``): every coarse voxel is fused, but only the ones
occupied or next to an occupied one query neighbours (``pvi_queries: near``; the release's ``all`` queries every
non-zero coarse voxel, 262,144 of them at 256 x 256 x 32, whose nearest supports are mostly far away); the first
``fuse_k`` points are averaged without the release's padding by the first point; the final ReLU on the logits is
left out; the point classifier has K outputs (class 0, unlabelled, is never a target) where the release has K - 1.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import Tensor, nn

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d
from distilkit.sparse.points import voxelize_flat
from distilkit.structures import VoxelGrid
from distilkit_adapters.js3cnet.model import near_queries, pixel_shuffle_3d, relation_features


def _bn(c: int) -> nn.BatchNorm1d:
    return nn.BatchNorm1d(c, eps=1e-4, momentum=0.1)  # the release's norm_fn


def _run(x: SparseConvTensor, layers: nn.Sequential) -> SparseConvTensor:
    """spconv's SparseSequential: sparse convolutions take the tensor, everything else its features."""
    for layer in layers:
        x = layer(x) if isinstance(layer, (SubMConv3d, SparseConv3d, SparseInverseConv3d)) \
            else x.replace_feature(layer(x.features))
    return x


class VGGBlock(nn.Module):
    def __init__(self, cin: int, cout: int, key: str) -> None:
        super().__init__()
        self.conv_layers = nn.Sequential(_bn(cin), nn.ReLU(),
                                         SubMConv3d(cin, cout, 3, padding=1, bias=False, indice_key=key))

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        return _run(x, self.conv_layers)


class UBlock(nn.Module):
    """One level of the release's spconv U-Net and, recursively, the levels below it."""

    def __init__(self, planes: list[int], reps: int = 1, level: int = 1) -> None:
        super().__init__()
        self.planes = planes
        key = f"subm{level}"
        self.blocks = nn.Sequential(OrderedDict((f"block{i}", VGGBlock(planes[0], planes[0], key))
                                                for i in range(reps)))
        if len(planes) > 1:
            self.conv = nn.Sequential(_bn(planes[0]), nn.ReLU(),
                                      SparseConv3d(planes[0], planes[1], 2, stride=2, bias=False,
                                                   indice_key=f"spconv{level}"))
            self.u = UBlock(planes[1:], reps, level + 1)
            self.deconv = nn.Sequential(_bn(planes[1]), nn.ReLU(),
                                        SparseInverseConv3d(planes[1], planes[0], 2, bias=False,
                                                            indice_key=f"spconv{level}"))
            self.blocks_tail = nn.Sequential(OrderedDict(
                (f"block{i}", VGGBlock(planes[0] * (2 if i == 0 else 1), planes[0], key)) for i in range(reps)))

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        out = self.blocks(x)
        if len(self.planes) == 1:
            return out
        up = _run(self.u(_run(out, self.conv)), self.deconv)
        return self.blocks_tail(out.replace_feature(torch.cat([out.features, up.features], 1)))


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
    def __init__(self, m: int, levels: int, num_classes: int) -> None:
        super().__init__()
        self.input_conv = nn.Sequential(SubMConv3d(1, m, 3, padding=1, bias=False, indice_key="subm1"))
        self.backbone_net = UBlock([m * (i + 1) for i in range(levels)])
        self.output_layer = nn.Sequential(_bn(m), nn.ReLU())
        self.linear = nn.Linear(m, num_classes)
        self.shape_embedding = ConvBNAct(m, m, linear=False)

    def forward(self, x: SparseConvTensor, point_rows: Tensor) -> tuple[Tensor, Tensor]:
        """Point logits and F_SE (P, m) of the points whose voxel rows are ``point_rows``."""
        feats = _run(self.backbone_net(_run(x, self.input_conv)), self.output_layer).features[point_rows]
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

    def aggregate(self, q_xyz: Tensor, s_xyz: Tensor, s_feat: Tensor) -> Tensor:
        """(Q, m): the relation-weighted mean of each query's k nearest supports' features."""
        if q_xyz.shape[0] == 0 or s_xyz.shape[0] == 0:
            return s_feat.new_zeros(q_xyz.shape[0], s_feat.shape[1])
        rel, idx = relation_features(q_xyz, s_xyz, self.k)
        w = self.relation_w(rel.permute(0, 2, 1))  # (Q, m, k)
        return (w * s_feat[idx].permute(0, 2, 1)).mean(2)


class CompletHead(nn.Module):
    def __init__(self, cin: int, m_seg: int, m: int, num_classes: int, k: int) -> None:
        super().__init__()
        self.Decoder = SSCNetDecoder(cin, m, num_classes)
        self.interaction_module = Interaction(m_seg, num_classes, k)
        self.upsample = nn.Sequential(nn.Conv3d(num_classes, num_classes * 8, 1), nn.BatchNorm3d(num_classes * 8))


def first_k_mean(values: Tensor, groups: Tensor, n_groups: int, k: int) -> Tensor:
    """(G, C): per group, the mean of ``values`` over its first ``k`` rows in input order (groups (P,) in [0, G))."""
    order = torch.sort(groups, stable=True).indices
    sorted_groups = groups[order]
    starts = torch.searchsorted(sorted_groups, sorted_groups, right=False)
    rank = torch.arange(len(order), device=groups.device) - starts
    chosen = order[rank < k]
    g = groups[chosen]
    total = values.new_zeros(n_groups, values.shape[1]).index_add_(0, g, values[chosen])
    count = torch.bincount(g, minlength=n_groups).clamp_min(1).to(values.dtype)
    return total / count[:, None]


class JS3CNetPaper(nn.Module):
    def __init__(self, num_classes: int, m: int = 16, levels: int = 7, ssc_m: int = 32, k: int = 8,
                 fuse_k: int = 5, pvi_queries: str = "near") -> None:
        super().__init__()
        self.k_classes, self.levels, self.fuse_k, self.pvi_queries = num_classes, levels, fuse_k, pvi_queries
        self.seg_head = SegHead(m, levels, num_classes)
        self.complet_head = CompletHead(num_classes - 1 + m, m, ssc_m, num_classes, k)

    def forward(self, points: Tensor, point_batch: Tensor, batch_size: int, grid: VoxelGrid) -> dict[str, Tensor]:
        # segmentation on the half-voxel grid, every point of the scan
        seg = voxelize_flat(points[:, :3], point_batch, batch_size, grid.voxel_size / 2, 2 ** (self.levels - 1),
                            points[:, 3:4], rounding="floor")
        point_logits, f_se = self.seg_head(seg.tensor, seg.point_rows)
        # voxel pooling into the completion grid: [labelled-class logits, F_SE] of each voxel's first fuse_k points
        idx, inside = grid.index(points[:, :3])
        x, y, z = grid.shape
        flat = ((point_batch[inside] * x + idx[inside, 0]) * y + idx[inside, 1]) * z + idx[inside, 2]
        uniq, rows = torch.unique(flat, return_inverse=True)
        both = torch.cat([point_logits[inside][:, 1:], f_se[inside]], 1)
        pooled = first_k_mean(both, rows, len(uniq), self.fuse_k)
        dense = pooled.new_zeros(batch_size * x * y * z, pooled.shape[1])
        dense[uniq] = pooled
        feat, coarse = self.complet_head.Decoder(dense.view(batch_size, x, y, z, -1).permute(0, 4, 1, 2, 3))
        # point-voxel interaction: supports = completion voxels with points, queries = coarse voxels
        query = near_queries(uniq, batch_size, grid.shape)
        if self.pvi_queries == "all":
            query = torch.ones_like(query)
        qc = query.nonzero()
        q_xyz = grid.coarsen(2).centers(qc[:, 1:])
        s_coords = torch.stack(torch.unravel_index(uniq, (batch_size, x, y, z)), 1)
        s_xyz = grid.centers(s_coords[:, 1:])
        s_feat = pooled[:, self.k_classes - 1:].detach()
        pvi = self.complet_head.interaction_module
        agg_q = torch.cat([pvi.aggregate(q_xyz[qc[:, 0] == b], s_xyz[s_coords[:, 0] == b],
                                         s_feat[s_coords[:, 0] == b]) for b in range(batch_size)])
        logits_cl = coarse.permute(0, 2, 3, 4, 1)  # (B, X/2, Y/2, Z/2, K)
        agg = logits_cl.new_zeros(*logits_cl.shape[:-1], agg_q.shape[1])
        agg[query] = agg_q  # batch-major, as qc
        fused = pvi.fuse_mlps(torch.cat([agg, logits_cl], -1).reshape(-1, agg.shape[-1] + self.k_classes))
        fused = fused.view(logits_cl.shape).permute(0, 4, 1, 2, 3)
        logits = pixel_shuffle_3d(self.complet_head.upsample(fused), 2)
        return {"logits": logits, "point_logits": point_logits, "ssc_coords": qc,
                "ssc_feats": feat.permute(0, 2, 3, 4, 1)[query], "ssc_dense": feat}
