"""SCPNet at ``size: paper`` computes what its release computes: weights set from a file in the release's layout
(bare ``cylinder_3d_*`` keys, spconv 1.x kernels (k0, k1, k2, in, out)), a few hundred points, and the logits
against an independent float64 reference of the release built here from the facts of issue 33 and the authors'
code: the dataloader's voxels (range / (grid - 1), x shifted by half its range), the featuriser, the dense completion,
the asymmetric U-Net with spconv 1.x's shared keys (:mod:`naive_sparse`). With ``semantics: spconv2`` every
convolution runs on its own kernel (Cylinder3D's spconv 2.x ports)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from naive_sparse import Spconv1
from distilkit.structures import VoxelGrid

GRID = VoxelGrid((0.0, -25.6, -2.0), (16, 16, 4), 3.2)  # the U-Net pools x, y by 16 and z by 4


def release_voxels_numpy(xyz: np.ndarray, grid: VoxelGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The release's ``voxel_dataset.__getitem__`` with a fixed volume: cut to [min, max], shift x by half its
    range, voxel = range / (grid - 1), index floor((clip(p) - min) / voxel), features [p - centre, p]."""
    lo = np.asarray(grid.origin, dtype=np.float64)
    hi = lo + np.asarray(grid.shape, dtype=np.float64) * grid.voxel_size
    keep = ~((xyz < lo) | (xyz > hi)).any(axis=1)
    p = xyz[keep].copy()  # the scan's precision (float32 from a .bin)
    bias = (hi[0] - lo[0]) / 2
    lo_s, hi_s = lo.copy(), hi.copy()
    lo_s[0] -= bias
    hi_s[0] -= bias
    p[:, 0] -= bias
    step = (hi_s - lo_s) / (np.asarray(grid.shape) - 1)
    ind = np.floor((np.clip(p, lo_s, hi_s) - lo_s) / step).astype(np.int64)
    centre = (ind.astype(np.float32) + 0.5) * step + lo_s
    return keep, ind, np.concatenate([p - centre, p.astype(np.float64)], axis=1)


def points(seed: int = 0, n: int = 300) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(GRID.origin)
    span = torch.tensor(GRID.shape) * GRID.voxel_size
    xyz = lo + torch.rand(n, 3, generator=g) * (span * 1.1) - 0.05 * span  # some outside the volume
    xyz[0] = torch.tensor([0.0, 0.5, 0.5])  # on the lower x bound: kept
    xyz[1] = lo + span  # float32(51.2) > 51.2: the release cuts it
    return torch.cat([xyz, torch.rand(n, 1, generator=g)], 1)


def test_the_release_voxels_follow_its_dataloader() -> None:
    from distilkit_adapters.scpnet.cylinder import point_voxels

    pts = points(1, 500)
    keep, ind, feats = release_voxels_numpy(pts[:, :3].numpy(), GRID)
    got_feats, vox, rows = point_voxels(pts, torch.zeros(len(pts), dtype=torch.long), GRID, "release")
    assert keep.sum() < len(pts) and keep[0] and not keep[1]
    assert torch.equal(vox[rows.long()][:, 1:].long(), torch.from_numpy(ind))
    assert torch.allclose(got_feats[:, :6].double(), torch.from_numpy(feats).double(), atol=1e-5)
    assert torch.equal(got_feats[:, 6], pts[torch.from_numpy(keep), 3])
    grid_feats, _, _ = point_voxels(pts, torch.zeros(len(pts), dtype=torch.long), GRID, "grid")
    assert float(got_feats[:, 3].min()) < -20 and float(grid_feats[:, 3].min()) >= 0  # x shifted by -25.6 / raw
    on_grid, _ = GRID.index(pts[torch.from_numpy(keep), :3])
    assert not torch.equal(on_grid, torch.from_numpy(ind))  # voxels of 3.2 * 16 / 15 m, not the grid's 3.2 m


def release_state(model: torch.nn.Module, seed: int) -> dict[str, torch.Tensor]:
    """Random weights in the release's layout: bare keys, spconv 1.x kernels, batch norms with running statistics,
    drawn in a checkpoint's precision (float32). ``model``: its keys and shapes (on any device, meta included)."""
    from distilkit.sparse.convert import spconv2_to_spconv1

    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, value in model.state_dict().items():
        name = key[len("net."):]
        if name.endswith("num_batches_tracked"):
            out[name] = torch.tensor(7)
            continue
        if name.endswith("running_var"):
            v = 0.5 + torch.rand(value.shape, generator=g)
        elif name.endswith("running_mean") or name.endswith("bias"):
            v = 0.3 * torch.randn(value.shape, generator=g)
        elif name.endswith(".weight") and value.dim() == 1:  # batch norm scales
            v = 1 + 0.2 * torch.randn(value.shape, generator=g)
        else:
            fan_in = value[0].numel() if value.dim() > 1 else 1
            v = torch.randn(value.shape, generator=g) * (1.5 / fan_in) ** 0.5
        sparse = name.startswith("cylinder_3d_spconv_seg.") and value.dim() == 5 and \
            not name.split(".")[1].startswith(("a_conv", "ch_conv", "res_"))
        out[name] = spconv2_to_spconv1(v) if sparse else v
    return out


def bn(x: torch.Tensor, r: dict, name: str) -> torch.Tensor:
    return (x - r[name + ".running_mean"]) / torch.sqrt(r[name + ".running_var"] + 1e-5) * r[name + ".weight"] + \
        r[name + ".bias"]


def leaky(x: torch.Tensor) -> torch.Tensor:
    return F.leaky_relu(x, 0.01)


def reference_dense(r: dict, pts: torch.Tensor) -> tuple[dict, torch.Tensor, list]:
    """The release's forward in float64 up to its sparse U-Net: (``r`` in float64, the U-Net's input features, their
    sites) — the featuriser, the voxel pooling and the dense completion."""
    r = {k: v.double() for k, v in r.items()}
    keep, ind, feats = release_voxels_numpy(pts[:, :3].numpy(), GRID)
    x = torch.from_numpy(np.concatenate([feats, pts[torch.from_numpy(keep), 3:4].numpy()], 1)).double()
    g = "cylinder_3d_generator."
    h = bn(x, r, g + "PPmodel.0")
    for lin, norm in ((1, 2), (4, 5), (7, 8)):
        h = torch.relu(bn(h @ r[f"{g}PPmodel.{lin}.weight"].t() + r[f"{g}PPmodel.{lin}.bias"], r, f"{g}PPmodel.{norm}"))
    h = h @ r[g + "PPmodel.10.weight"].t() + r[g + "PPmodel.10.bias"]
    pooled: dict[tuple, torch.Tensor] = {}
    for c, f in zip(map(tuple, ind.tolist()), h):
        pooled[c] = f if c not in pooled else torch.maximum(pooled[c], f)
    dense = torch.zeros(1, 32, *GRID.shape, dtype=torch.float64)
    for c, f in pooled.items():
        dense[0, :, c[0], c[1], c[2]] = torch.relu(f @ r[g + "fea_compression.0.weight"].t()
                                                   + r[g + "fea_compression.0.bias"])
    s = "cylinder_3d_spconv_seg."

    def dconv(name: str, t: torch.Tensor) -> torch.Tensor:
        w = r[f"{s}{name}.0.weight"]
        return torch.relu(F.conv3d(t, w, padding=w.shape[-1] // 2))

    x1 = dconv("a_conv1", dense)
    x2, x3, x4 = dconv("a_conv2", x1), dconv("a_conv3", x1), dconv("a_conv4", x1)
    t1 = torch.cat([x2, x3, x4], 1)
    x5, x6, x7 = dconv("a_conv5", t1), dconv("a_conv6", t1), dconv("a_conv7", t1)
    y = dense + dconv("ch_conv1", torch.cat([x1, x2, x3, x4, x5, x6, x7], 1)) + dconv("res_1", dense) + \
        dconv("res_2", dense) + dconv("res_3", dense)
    active = y[0].abs().sum(0).nonzero().tolist()
    coords = [(0, *c) for c in active]
    feats0 = torch.stack([y[0, :, c[1], c[2], c[3]] for c in coords])
    return r, feats0, coords


def reference(r: dict, pts: torch.Tensor, shared: bool, dense: tuple | None = None) -> torch.Tensor:
    """The release's forward in float64 (eval mode), from its state dict ``r``; ``shared``: SCPNet's shared keys.
    ``dense``: :func:`reference_dense`'s result for ``r`` and ``pts`` where already computed (it does not depend on
    ``shared``)."""
    r, feats0, coords = dense if dense is not None else reference_dense(r, pts)
    s = "cylinder_3d_spconv_seg."
    net = Spconv1()

    def k(base: str, i: int) -> str:
        return base if shared else f"{base}{i}"

    def act_bn(t, conv, norm, key, cs, prefix):
        return bn(leaky(net.subm(t, cs, r[f"{prefix}{conv}.weight"], key)), r, prefix + norm)

    def res(t, cs, p, key, order):  # ResContextBlock (order 1x3x3 first) / ResBlock (3x1x3 first)
        sc = act_bn(act_bn(t, "conv1", "bn0", k(key + "bef", 1), cs, p), "conv1_2", "bn0_2", k(key + "bef", 2), cs, p)
        ra = act_bn(act_bn(t, "conv2", "bn1", k(key + "bef", 3), cs, p), "conv3", "bn2", k(key + "bef", 4), cs, p)
        return ra + sc

    shapes, levels = [GRID.shape], []
    t, cs = res(feats0, coords, s + "downCntx.", "pre", 0), coords
    for i, (blk, stride) in enumerate([("resBlock2", (2, 2, 2)), ("resBlock3", (2, 2, 2)), ("resBlock4", (2, 2, 1)),
                                       ("resBlock5", (2, 2, 1))]):
        b = res(t, cs, f"{s}{blk}.", f"down{i + 2}", 1)
        levels.append((b, cs))
        t, cs, shape = net.strided(b, cs, shapes[-1], r[f"{s}{blk}.pool.weight"], stride, (1, 1, 1), f"down{i + 2}")
        shapes.append(shape)
    for i in range(4):
        p, key = f"{s}upBlock{i}.", f"up{i}"
        skip, skip_cs = levels[3 - i]
        up = act_bn(t, "trans_dilao", "trans_bn", key + "new_up", cs, p)
        up, cs = net.inverse(up, r[p + "up_subm.weight"], f"down{5 - i}")
        up = up + skip
        for j, (conv, norm) in enumerate([("conv1", "bn1"), ("conv2", "bn2"), ("conv3", "bn3")]):
            up = act_bn(up, conv, norm, key if shared else f"{key}up{j + 1}", cs, p)
        t = up
    p = s + "ReconNet."
    gates = [torch.sigmoid(bn(net.subm(t, cs, r[f"{p}{conv}.weight"], k("reconbef", j + 1)), r, p + norm))
             for j, (conv, norm) in enumerate([("conv1", "bn0"), ("conv1_2", "bn0_2"), ("conv1_3", "bn0_3")])]
    recon = (gates[0] + gates[1] + gates[2]) * t
    logits = net.subm(torch.cat([recon, t], 1), cs, r[s + "logits.weight"], "logit") + r[s + "logits.bias"]
    out = torch.zeros(1, logits.shape[1], *GRID.shape, dtype=torch.float64)
    for c, f in zip(cs, logits):
        out[0, :, c[1], c[2], c[3]] = f
    return out


def adapter(semantics: str) -> torch.nn.Module:
    """The adapter's loading path around a paper network on GRID."""
    from distilkit_adapters.scpnet.adapter import SCPNetAdapter
    from distilkit_adapters.scpnet.cylinder import SCPNetPaper

    model = SCPNetAdapter.__new__(SCPNetAdapter)
    torch.nn.Module.__init__(model)
    model.net = SCPNetPaper(20, semantics=semantics)
    return model


@pytest.fixture(scope="module")
def release(tmp_path_factory: pytest.TempPathFactory):
    """One release checkpoint (random weights, seed 3) for both key semantics (their state dicts have the same keys
    and shapes), the file it is saved in as the adapter reads it, and the reference's logits with SCPNet's shared
    keys and without (``shared`` True / False), each computed once (their dense part, which the keys do not touch,
    once for both)."""
    torch.manual_seed(0)
    with torch.device("meta"):  # its keys and shapes only: nothing allocated
        layout = adapter("spconv1")
    state = release_state(layout, seed=3)
    path = tmp_path_factory.mktemp("scpnet_release") / "scpnet_release.pt"
    torch.save(state, path)
    pts = points().double()
    dense = reference_dense(state, pts)  # the same up to the U-Net for both
    from distilkit_adapters.scpnet.adapter import SCPNetAdapter

    weights = SCPNetAdapter.read_weights(str(path))  # the file as the adapter reads it (both semantics load it)
    return state, weights, {shared: reference(state, pts, shared=shared, dense=dense) for shared in (True, False)}


@pytest.mark.xdist_group("scpnet_release")  # one worker builds the shared checkpoint and references
@pytest.mark.parametrize("semantics", ["spconv1", "spconv2"])
def test_a_release_checkpoint_gives_the_releases_logits(semantics, release, device) -> None:
    """The file loads with every key used and fitting (strict); the network's logits (on --device) are the
    reference's of its semantics (spconv1: shared keys) to 1e-9 on the same active sites, more than 300; the other
    semantics' reference differs."""
    from distilkit.weights import load_weights

    state, weights, references = release
    torch.manual_seed(0)
    model = adapter(semantics)
    assert state["cylinder_3d_spconv_seg.upBlock0.conv3.weight"].shape == (3, 3, 3, 512, 512)
    assert load_weights(model, weights, True, "release") == []
    model = model.double().eval().to(device)
    pts = points().double()
    with torch.no_grad():
        _, _, logits = model.net(pts.to(device), torch.zeros(len(pts), dtype=torch.long, device=device), 1, GRID)
        logits = logits.cpu()
    want = references[semantics == "spconv1"]
    active = want.abs().sum(1) > 0
    assert int(active.sum()) > 300 and torch.equal(logits.abs().sum(1) > 0, active)
    assert torch.allclose(logits, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))
    other = references[semantics != "spconv1"]  # the two releases differ
    assert not torch.allclose(other, want, rtol=1e-3, atol=1e-3 * float(want.abs().max()))
