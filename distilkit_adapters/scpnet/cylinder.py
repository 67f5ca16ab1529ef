"""SCPNet at the paper's size (Xia et al., CVPR 2023; SCPNet/Codes-for-SCPNet, built on Cylinder3D), with the
release's module names so that its state dicts load (``weights.read_scpnet``):

* ``cylinder_3d_generator`` — the point featuriser: BN, then Linear 7 -> 64 -> 128 -> 256 -> 256 with BN + ReLU
  (``PPmodel``), max over each voxel's points, Linear 256 -> 32 + ReLU (``fea_compression``); point features are the
  offset to the voxel centre, the position and the intensity (:func:`release_point_voxels`: the release's voxels);
* ``cylinder_3d_spconv_seg`` — the completion sub-network as released (dense ``nn.Conv3d`` without bias or BN:
  ``a_conv1`` 3^3 -> ``a_conv2..4`` 3/5/7 -> ``a_conv5..7`` 3/5/7 on their concatenation -> ``ch_conv1`` 1^3 over all
  seven, plus ``res_1..3`` 3/5/7 on the input, summed with it), its non-zero voxels, then Cylinder3D's asymmetric
  sparse U-Net: ``downCntx`` (asymmetric residual context), ``resBlock2..5`` (asymmetric residual blocks, each
  pooling by a stride-2 sparse convolution: x, y and z in the first two, x and y in the last two), ``upBlock0..3``
  (3^3 convolution, the inverse of the matching pooling, the skip added, 1x3x3 / 3x1x3 / 3^3 convolutions),
  ``ReconNet`` (the reconstruction block: 3x1x1, 1x3x1 and 1x1x3 gates, sigmoid, times the input) and ``logits``
  (3^3 submanifold convolution with bias on [ReconNet, upBlock3]); every convolution a ``distilkit.sparse`` one
  (spconv 2.x's weight layout), every activation LeakyReLU then BatchNorm as released.

Two releases compute different things from the same names (``semantics``):

* ``spconv1`` — SCPNet's release (``import spconv``, spconv 1.2.1): the four convolutions of a block share one
  ``indice_key`` (``prebef``, ``down2bef``, ...; an UpBlock's ``conv1..3`` share ``up0``...; the ReconBlock's gates
  ``reconbef``), and spconv 1.x reuses the first one's neighbourhood for the others whatever their kernel. So in a
  ``...bef`` block all four run on the first one's 1x3x3 or 3x1x3 offsets, an UpBlock's ``conv2`` and ``conv3`` on
  1x3x3 offsets (``conv3`` with its 3^3 kernel's slice ``[:, 0]``), the three ReconBlock gates on 3x1x1 offsets.
  SCPNet's checkpoints were trained this way.
* ``spconv2`` — Cylinder3D's ports to spconv 2.x (``import spconv.pytorch``): a key per convolution (``bef1`` ...
  ``bef4``, ``up1`` ... ``up3``), every kernel as written; their checkpoints need this.

The logits are the dense grid of the sparse output: 0 at voxels outside the completed set, as in the release.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn

from distilkit.sparse import SparseConv3d, SparseConvTensor, SparseInverseConv3d, SubMConv3d, name_modules
from distilkit.sparse.conv import Semantics
from distilkit.structures import SparseVoxels, VoxelGrid


def _subm(cin: int, cout: int, kernel: tuple[int, int, int], key: str, semantics: Semantics,
          bias: bool = False) -> SubMConv3d:
    return SubMConv3d(cin, cout, kernel, padding=tuple(k // 2 for k in kernel), bias=bias, indice_key=key,
                      semantics=semantics)


def _key(base: str, i: int, semantics: Semantics) -> str:
    """The i-th convolution's key in a block whose keys start with ``base``: SCPNet's release shares ``base``, the
    spconv 2.x ports number them (``base1``, ``base2``, ...)."""
    return base if semantics == "spconv1" else f"{base}{i}"


def _act_bn(x: SparseConvTensor, act: nn.Module, bn: nn.Module) -> SparseConvTensor:
    """Cylinder3D's order: the activation, then the batch norm, on the features."""
    return x.replace_feature(bn(act(x.features)))


class ResContextBlock(nn.Module):
    def __init__(self, cin: int, cout: int, key: str, semantics: Semantics) -> None:
        super().__init__()
        k = [_key(key + "bef", i, semantics) for i in (1, 2, 3, 4)]
        self.conv1, self.bn0, self.act1 = _subm(cin, cout, (1, 3, 3), k[0], semantics), nn.BatchNorm1d(cout), \
            nn.LeakyReLU()
        self.conv1_2, self.bn0_2, self.act1_2 = (_subm(cout, cout, (3, 1, 3), k[1], semantics), nn.BatchNorm1d(cout),
                                                 nn.LeakyReLU())
        self.conv2, self.act2, self.bn1 = _subm(cin, cout, (3, 1, 3), k[2], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.conv3, self.act3, self.bn2 = (_subm(cout, cout, (1, 3, 3), k[3], semantics), nn.LeakyReLU(),
                                           nn.BatchNorm1d(cout))

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        shortcut = _act_bn(self.conv1_2(_act_bn(self.conv1(x), self.act1, self.bn0)), self.act1_2, self.bn0_2)
        res = _act_bn(self.conv3(_act_bn(self.conv2(x), self.act2, self.bn1)), self.act3, self.bn2)
        return res.replace_feature(res.features + shortcut.features)


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, key: str, height_pooling: bool, semantics: Semantics) -> None:
        super().__init__()
        k = [_key(key + "bef", i, semantics) for i in (1, 2, 3, 4)]
        self.conv1, self.act1, self.bn0 = _subm(cin, cout, (3, 1, 3), k[0], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.conv1_2, self.act1_2, self.bn0_2 = (_subm(cout, cout, (1, 3, 3), k[1], semantics), nn.LeakyReLU(),
                                                 nn.BatchNorm1d(cout))
        self.conv2, self.act2, self.bn1 = _subm(cin, cout, (1, 3, 3), k[2], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.conv3, self.act3, self.bn2 = (_subm(cout, cout, (3, 1, 3), k[3], semantics), nn.LeakyReLU(),
                                           nn.BatchNorm1d(cout))
        self.pool = SparseConv3d(cout, cout, 3, stride=2 if height_pooling else (2, 2, 1), padding=1, indice_key=key,
                                 bias=False, semantics=semantics)

    def forward(self, x: SparseConvTensor) -> tuple[SparseConvTensor, SparseConvTensor]:
        shortcut = _act_bn(self.conv1_2(_act_bn(self.conv1(x), self.act1, self.bn0)), self.act1_2, self.bn0_2)
        res = _act_bn(self.conv3(_act_bn(self.conv2(x), self.act2, self.bn1)), self.act3, self.bn2)
        res = res.replace_feature(res.features + shortcut.features)
        return self.pool(res), res


class UpBlock(nn.Module):
    def __init__(self, cin: int, cout: int, key: str, up_key: str, semantics: Semantics) -> None:
        super().__init__()
        k = [_key(key + ("" if semantics == "spconv1" else "up"), i, semantics) for i in (1, 2, 3)]
        self.trans_dilao, self.trans_act, self.trans_bn = (_subm(cin, cout, (3, 3, 3), key + "new_up", semantics),
                                                           nn.LeakyReLU(), nn.BatchNorm1d(cout))
        self.conv1, self.act1, self.bn1 = _subm(cout, cout, (1, 3, 3), k[0], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.conv2, self.act2, self.bn2 = _subm(cout, cout, (3, 1, 3), k[1], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.conv3, self.act3, self.bn3 = _subm(cout, cout, (3, 3, 3), k[2], semantics), nn.LeakyReLU(), \
            nn.BatchNorm1d(cout)
        self.up_subm = SparseInverseConv3d(cout, cout, 3, indice_key=up_key, bias=False, semantics=semantics)

    def forward(self, x: SparseConvTensor, skip: SparseConvTensor) -> SparseConvTensor:
        up = self.up_subm(_act_bn(self.trans_dilao(x), self.trans_act, self.trans_bn))
        up = up.replace_feature(up.features + skip.features)
        up = _act_bn(self.conv1(up), self.act1, self.bn1)
        up = _act_bn(self.conv2(up), self.act2, self.bn2)
        return _act_bn(self.conv3(up), self.act3, self.bn3)


class ReconBlock(nn.Module):
    def __init__(self, cin: int, cout: int, key: str, semantics: Semantics) -> None:
        super().__init__()
        k = [_key(key + "bef", i, semantics) for i in (1, 2, 3)]
        self.conv1, self.bn0, self.act1 = _subm(cin, cout, (3, 1, 1), k[0], semantics), nn.BatchNorm1d(cout), \
            nn.Sigmoid()
        self.conv1_2, self.bn0_2, self.act1_2 = (_subm(cin, cout, (1, 3, 1), k[1], semantics), nn.BatchNorm1d(cout),
                                                 nn.Sigmoid())
        self.conv1_3, self.bn0_3, self.act1_3 = (_subm(cin, cout, (1, 1, 3), k[2], semantics), nn.BatchNorm1d(cout),
                                                 nn.Sigmoid())

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        gates = [act(bn(conv(x).features)) for conv, bn, act in ((self.conv1, self.bn0, self.act1),
                                                                 (self.conv1_2, self.bn0_2, self.act1_2),
                                                                 (self.conv1_3, self.bn0_3, self.act1_3))]
        return x.replace_feature((gates[0] + gates[1] + gates[2]) * x.features)


def _dense(cin: int, cout: int, k: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv3d(cin, cout, k, 1, padding=k // 2, bias=False), nn.ReLU())


class Asymm3dSpconv(nn.Module):
    """``cylinder_3d_spconv_seg``: the completion sub-network (dense, as released) and the asymmetric U-Net."""

    def __init__(self, num_input_features: int = 32, init_size: int = 32, nclasses: int = 20,
                 semantics: Semantics = "spconv1", completion: bool = True) -> None:
        """``completion=False``: Cylinder3D's U-Net alone (no completion sub-network; the Dean-Labeler's)."""
        super().__init__()
        c, sem = init_size, semantics
        if completion:
            self.a_conv1, self.a_conv2 = _dense(c, c, 3), _dense(c, c, 3)
            self.a_conv3, self.a_conv4 = _dense(c, c, 5), _dense(c, c, 7)
            self.a_conv5, self.a_conv6, self.a_conv7 = _dense(3 * c, c, 3), _dense(3 * c, c, 5), _dense(3 * c, c, 7)
            self.ch_conv1 = _dense(7 * c, c, 1)
            self.res_1, self.res_2, self.res_3 = _dense(c, c, 3), _dense(c, c, 5), _dense(c, c, 7)
        self.downCntx = ResContextBlock(num_input_features, c, "pre", sem)
        self.resBlock2 = ResBlock(c, 2 * c, "down2", True, sem)
        self.resBlock3 = ResBlock(2 * c, 4 * c, "down3", True, sem)
        self.resBlock4 = ResBlock(4 * c, 8 * c, "down4", False, sem)
        self.resBlock5 = ResBlock(8 * c, 16 * c, "down5", False, sem)
        self.upBlock0 = UpBlock(16 * c, 16 * c, "up0", "down5", sem)
        self.upBlock1 = UpBlock(16 * c, 8 * c, "up1", "down4", sem)
        self.upBlock2 = UpBlock(8 * c, 4 * c, "up2", "down3", sem)
        self.upBlock3 = UpBlock(4 * c, 2 * c, "up3", "down2", sem)
        self.ReconNet = ReconBlock(2 * c, 2 * c, "recon", sem)
        self.logits = _subm(4 * c, nclasses, (3, 3, 3), "logit", sem, bias=True)

    def complete(self, dense: Tensor) -> Tensor:
        """The completion sub-network as released: x + ch_conv1([x1..x7]) + res_1(x) + res_2(x) + res_3(x)."""
        x1 = self.a_conv1(dense)
        x2, x3, x4 = self.a_conv2(x1), self.a_conv3(x1), self.a_conv4(x1)
        t1 = torch.cat((x2, x3, x4), 1)
        x5, x6, x7 = self.a_conv5(t1), self.a_conv6(t1), self.a_conv7(t1)
        y0 = self.ch_conv1(torch.cat((x1, x2, x3, x4, x5, x6, x7), 1))
        return dense + y0 + self.res_1(dense) + self.res_2(dense) + self.res_3(dense)

    def segment(self, x: SparseConvTensor) -> SparseConvTensor:
        return self.logits(self.segment_features(x))

    def segment_features(self, x: SparseConvTensor) -> SparseConvTensor:
        """The U-Net's last features, [ReconNet, upBlock3] (4 x init_size channels), which ``logits`` reads."""
        x = self.downCntx(x)
        down1c, down1b = self.resBlock2(x)
        down2c, down2b = self.resBlock3(down1c)
        down3c, down3b = self.resBlock4(down2c)
        down4c, down4b = self.resBlock5(down3c)
        up4e = self.upBlock0(down4c, down4b)
        up3e = self.upBlock1(up4e, down3b)
        up2e = self.upBlock2(up3e, down2b)
        up1e = self.upBlock3(up2e, down1b)
        up0e = self.ReconNet(up1e)
        return up0e.replace_feature(torch.cat((up0e.features, up1e.features), 1))


class CylinderFea(nn.Module):
    """``cylinder_3d_generator``: per-point MLP, max per voxel, compression to the sparse network's width."""

    def __init__(self, fea_dim: int = 7, out_pt_fea_dim: int = 256, fea_compre: int = 32) -> None:
        super().__init__()
        self.PPmodel = nn.Sequential(
            nn.BatchNorm1d(fea_dim), nn.Linear(fea_dim, 64), nn.BatchNorm1d(64), nn.ReLU(),
            nn.Linear(64, 128), nn.BatchNorm1d(128), nn.ReLU(), nn.Linear(128, 256), nn.BatchNorm1d(256), nn.ReLU(),
            nn.Linear(256, out_pt_fea_dim))
        self.fea_compression = nn.Sequential(nn.Linear(out_pt_fea_dim, fea_compre), nn.ReLU())

    def forward(self, features: Tensor, voxel_rows: Tensor, voxels: int) -> Tensor:
        """(P, 7) point features, each point's voxel row -> (voxels, fea_compre)."""
        h = self.PPmodel(features)
        pooled = h.new_full((voxels, h.shape[1]), float("-inf")).scatter_reduce(
            0, voxel_rows[:, None].expand_as(h), h, "amax", include_self=True)
        return self.fea_compression(pooled)


Voxelization = Literal["release", "grid"]


def release_voxels(xyz: Tensor, grid: VoxelGrid) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """SCPNet's release (``voxel_dataset`` in ``dataloader/dataset_semantickitti.py`` of Codes-for-SCPNet, as in
    Cylinder3D) over the grid's volume [lo, hi]: the points with lo <= p <= hi, x shifted by half the x extent
    (-25.6 m; in the scan's own precision, as numpy shifts the float32 array in place), voxels of (hi - lo) /
    (shape - 1) per axis (0.2008, 0.2008, 0.2065 m for SemanticKITTI's 256 x 256 x 32) and index
    floor((p - lo) / voxel) in float64, as numpy computes it there. Returns (the kept points' mask, their (M, 3)
    indices, their offsets to the voxel centre, their shifted positions), the last two in float64."""
    f64 = dict(dtype=torch.float64, device=xyz.device)
    lo = torch.tensor(grid.origin, **f64)
    extent = torch.tensor(grid.shape, **f64) * grid.voxel_size
    hi = lo + extent
    keep = ((xyz >= lo) & (xyz <= hi)).all(dim=1)
    shift = torch.zeros(3, **f64)
    shift[0] = extent[0] / 2
    shifted = (xyz[keep] - shift.to(xyz.dtype)).double()
    lo, hi = lo - shift, hi - shift
    step = extent / (torch.tensor(grid.shape, **f64) - 1)
    idx = torch.floor((torch.maximum(torch.minimum(shifted, hi), lo) - lo) / step).long()
    centre = (idx.double() + 0.5) * step + lo
    return keep, idx, shifted - centre, shifted


def point_voxels(points: Tensor, point_batch: Tensor, grid: VoxelGrid,
                 voxelization: Voxelization = "release") -> tuple[Tensor, Tensor, Tensor]:
    """(the points' 7 features: offset to the voxel centre, position, intensity; the (N, 4) int32 voxel indices;
    each kept point's voxel row). ``release``: :func:`release_voxels`; ``grid``: the grid's own voxels (0.2 m) and
    raw positions, the points whose voxel is inside it."""
    if voxelization == "release":
        inside, idx, offset, position = release_voxels(points[:, :3], grid)
        pts = points[inside]
        feats = torch.cat([offset.to(pts.dtype), position.to(pts.dtype), pts[:, 3:4]], dim=1)
    else:
        idx, inside = grid.index(points[:, :3])
        pts, idx = points[inside], idx[inside]
        centre = grid.centers(idx).to(pts.dtype)
        feats = torch.cat([pts[:, :3] - centre, pts[:, :3], pts[:, 3:4]], dim=1)
    batch = point_batch[inside].long()
    keys = ((batch * grid.shape[0] + idx[:, 0]) * grid.shape[1] + idx[:, 1]) * grid.shape[2] + idx[:, 2]
    unique, rows = torch.unique(keys, return_inverse=True)
    vox = torch.stack([unique // (grid.shape[0] * grid.shape[1] * grid.shape[2]),
                       (unique // (grid.shape[1] * grid.shape[2])) % grid.shape[0],
                       (unique // grid.shape[2]) % grid.shape[1], unique % grid.shape[2]], dim=1)
    return feats, vox.int(), rows


class SCPNetPaper(nn.Module):
    """SCPNet as released (``cylinder_asym``): featuriser, dense completion, sparse segmentation."""

    def __init__(self, num_classes: int = 20, init_size: int = 32, semantics: Semantics = "spconv1",
                 voxelization: Voxelization = "release") -> None:
        super().__init__()
        self.voxelization = voxelization
        self.cylinder_3d_generator = CylinderFea(fea_compre=init_size)
        self.cylinder_3d_spconv_seg = Asymm3dSpconv(init_size, init_size, num_classes, semantics)
        name_modules(self)

    def forward(self, points: Tensor, point_batch: Tensor, batch_size: int,
                grid: VoxelGrid) -> tuple[SparseVoxels, Tensor, Tensor]:
        """(the completed volume's non-zero voxels, that volume (B, C, X, Y, Z), the logits (B, K, X, Y, Z))."""
        feats, vox, rows = point_voxels(points, point_batch, grid, self.voxelization)
        voxel_feats = self.cylinder_3d_generator(feats, rows.long(), len(vox))
        seg = self.cylinder_3d_spconv_seg
        dense = SparseConvTensor(voxel_feats, vox, grid.shape, batch_size).dense()
        completed = seg.complete(dense)
        active = completed.detach().abs().sum(dim=1) > 0
        indices = active.nonzero()
        sparse = SparseConvTensor(completed.permute(0, 2, 3, 4, 1)[active], indices.int(), grid.shape, batch_size)
        logits = seg.segment(sparse).dense()
        return SparseVoxels(indices, sparse.features, tuple(grid.shape), grid), completed, logits


__all__ = ["Asymm3dSpconv", "CylinderFea", "SCPNetPaper", "point_voxels", "release_voxels"]
