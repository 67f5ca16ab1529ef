"""JS3C-Net at ``size: paper`` is the release's network: a file in the release's layout (the keys and shapes of
``J3SC_Net.state_dict()`` enumerated here from the authors' model definitions: SparseConvNet's UNet naming, no
``num_batches_tracked`` in scn's batch norms) loads with every key used or reported, and the logits equal an
independent float64 reference of the release's forward (naive SparseConvNet rules from :mod:`naive_sparse`, the
voxel pooling with its padding, the z + 1, SSCNet's decoder, the point-voxel interaction, the final ReLU)."""

from __future__ import annotations

from itertools import product

import pytest
import torch
import torch.nn.functional as F

from naive_sparse import SparseConvNet as SCN
from distilkit.structures import VoxelGrid

GRID = VoxelGrid((0.0, -25.6, -2.0), (16, 16, 4), 0.8)
SEG_VOXEL = 0.2
M, LEVELS, K = 16, 7, 20
DECODER = {"b1_conv1": (K - 1 + M, 16, 7), "b1_conv2": (16, 32, 3), "b1_conv3": (32, 32, 3), "b1_res": (16, 32, 3),
           "b2_conv1": (32, 32, 3), "b2_conv2": (32, 32, 3), "b2_res": (32, 32, 3), "b3_conv1": (32, 32, 3),
           "b3_conv2": (32, 32, 3), "b4_conv1": (32, 32, 3), "b4_conv2": (32, 32, 3), "b5_conv1": (32, 32, 3),
           "b5_conv2": (32, 32, 3), "pre_conv1": (96, 64, 1)}


def bn(name: str, n: int, tracked: bool) -> dict[str, tuple[int, ...]]:
    out = {f"{name}.{p}": (n,) for p in ("weight", "bias", "running_mean", "running_var")}
    return {**out, f"{name}.num_batches_tracked": ()} if tracked else out


def unet_keys(prefix: str, planes: list[int]) -> dict[str, tuple[int, ...]]:
    """scn.UNet(3, 1, planes, residual_blocks=True)'s parameters: a block at 0 (+ AddTable at 1), then the skip
    table at 2 (2.1: BN, conv, the next levels, BN, deconv; JoinTable at 3) and a block from 2 n at 4."""
    def block(p: str, a: int, b: int) -> dict[str, tuple[int, ...]]:
        out = {f"{p}0.weight": (a, b)} if a != b else {}
        return {**out, **bn(f"{p}1.0", a, False), f"{p}1.1.weight": (27, 1, a, b), **bn(f"{p}1.2", b, False),
                f"{p}1.3.weight": (27, 1, b, b)}

    keys = block(prefix + "0.", planes[0], planes[0])
    if len(planes) > 1:
        keys |= {**bn(prefix + "2.1.0", planes[0], False), prefix + "2.1.1.weight": (8, 1, planes[0], planes[1]),
                 **unet_keys(prefix + "2.1.2.", planes[1:]), **bn(prefix + "2.1.3", planes[1], False),
                 prefix + "2.1.4.weight": (8, 1, planes[1], planes[0]), **block(prefix + "4.", 2 * planes[0], planes[0])}
    return keys


def release_shapes() -> dict[str, tuple[int, ...]]:
    s = "seg_head."
    keys = {f"{s}sparseModel.1.weight": (27, 1, 1, M), **unet_keys(f"{s}sparseModel.2.", [M * (i + 1) for i in
                                                                                           range(LEVELS)]),
            **bn(f"{s}sparseModel.3", M, False), f"{s}linear.weight": (K - 1, M), f"{s}linear.bias": (K - 1,),
            f"{s}shape_embedding.conv.weight": (M, M, 1), **bn(f"{s}shape_embedding.bn.bn", M, True)}
    c = "complet_head."
    for name, (cin, cout, k) in DECODER.items():
        keys |= {f"{c}Decoder.{name}.0.weight": (cout, cin, k, k, k), f"{c}Decoder.{name}.0.bias": (cout,),
                 **bn(f"{c}Decoder.{name}.1", cout, True)}
    keys |= {f"{c}Decoder.pre_conv2.0.weight": (K, 64, 1, 1, 1), f"{c}Decoder.pre_conv2.0.bias": (K,),
             f"{c}upsample.0.weight": (8 * K, K, 1, 1, 1), f"{c}upsample.0.bias": (8 * K,),
             **bn(f"{c}upsample.1", 8 * K, True),
             f"{c}interaction_module.relation_w.conv.weight": (M, 10, 1),
             **bn(f"{c}interaction_module.relation_w.bn.bn", M, True),
             f"{c}interaction_module.fuse_mlps.fc.weight": (K, M + K),
             **bn(f"{c}interaction_module.fuse_mlps.bn.bn", K, True),
             "voxelpool.relation_w.weight": (M, 10, 1), "voxelpool.relation_w.bias": (M,),
             "seg_sigmas_sq": (1,), "complet_sigmas_sq": (1,)}
    return keys


def release_file(seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    out = {}
    for key, shape in release_shapes().items():
        if key.endswith("num_batches_tracked"):
            out[key] = torch.tensor(11)
        elif key.endswith("running_var"):
            out[key] = 0.5 + torch.rand(shape, generator=g)
        elif key.endswith(("running_mean", "bias")):
            out[key] = 0.2 * torch.randn(shape, generator=g)
        elif len(shape) == 1:  # batch-norm scales, the sigmas
            out[key] = 1 + 0.2 * torch.randn(shape, generator=g)
        else:
            if len(shape) == 4:  # scn's (volume, 1, in, out)
                fan_in = shape[0] * shape[2]
            elif "sparseModel" in key:  # NetworkInNetwork (in, out)
                fan_in = shape[0]
            else:  # torch's (out, in, ...)
                fan_in = int(torch.tensor(shape[1:]).prod())
            out[key] = torch.randn(shape, generator=g) * (1.5 / max(fan_in, 1)) ** 0.5
    return out


def points(seed: int = 0, n: int = 400) -> torch.Tensor:
    """Points in a box of the grid (some above it, raised past it by the z + 1, or outside), intensities."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor(GRID.origin)
    span = torch.tensor(GRID.shape) * GRID.voxel_size
    xyz = lo + torch.rand(n, 3, generator=g) * span * torch.tensor([1.0, 1.0, 1.1])
    return torch.cat([xyz, torch.rand(n, 1, generator=g)], 1).double()


def reference(r: dict[str, torch.Tensor], pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(point logits (P, K - 1), logits (1, K, X, Y, Z)) of the release in float64, eval mode."""
    r = {k: v.double() for k, v in r.items()}

    def scn_bn(x, name):
        return torch.relu((x - r[name + ".running_mean"]) / torch.sqrt(r[name + ".running_var"] + 1e-4)
                          * r[name + ".weight"] + r[name + ".bias"])

    def torch_bn(x, name, dims=1):
        shape = (-1,) + (1,) * (dims - 1)
        return ((x - r[name + ".running_mean"].view(shape)) / torch.sqrt(r[name + ".running_var"].view(shape) + 1e-5)
                * r[name + ".weight"].view(shape) + r[name + ".bias"].view(shape))

    # segmentation: voxels of SEG_VOXEL, each one's mean intensity
    cells = [tuple([0] + [int(v) for v in torch.floor(p[:3] / SEG_VOXEL).tolist()]) for p in pts]
    coords = sorted(set(cells))
    row = {c: i for i, c in enumerate(coords)}
    intensity = torch.zeros(len(coords), 1, dtype=torch.float64)
    count = torch.zeros(len(coords), dtype=torch.float64)
    for c, p in zip(cells, pts):
        intensity[row[c], 0] += p[3]
        count[row[c]] += 1
    x = SCN.subm(intensity / count[:, None], coords, r["seg_head.sparseModel.1.weight"])

    def block(p, h, cs, a, b):
        short = h if a == b else h @ r[p + "0.weight"]
        y = SCN.subm(scn_bn(h, p + "1.0"), cs, r[p + "1.1.weight"])
        return short + SCN.subm(scn_bn(y, p + "1.2"), cs, r[p + "1.3.weight"])

    def unet(p, h, cs, planes):
        h = block(p + "0.", h, cs, planes[0], planes[0])
        if len(planes) == 1:
            return h
        down, cd, pairs = SCN.down(scn_bn(h, p + "2.1.0"), cs, r[p + "2.1.1.weight"])
        down = scn_bn(unet(p + "2.1.2.", down, cd, planes[1:]), p + "2.1.3")
        up = SCN.up(down, pairs, len(cs), r[p + "2.1.4.weight"])
        return block(p + "4.", torch.cat([h, up], 1), cs, 2 * planes[0], planes[0])

    x = scn_bn(unet("seg_head.sparseModel.2.", x, coords, [M * (i + 1) for i in range(LEVELS)]),
               "seg_head.sparseModel.3")
    f = x[[row[c] for c in cells]]
    s = "seg_head."
    f_se = F.leaky_relu(torch_bn(f @ r[s + "shape_embedding.conv.weight"][:, :, 0].t(), s + "shape_embedding.bn.bn"),
                        0.2)
    point_logits = (f + f_se) @ r[s + "linear.weight"].t() + r[s + "linear.bias"]
    # voxel pooling: spconv's VoxelGenerator voxel, z + 1, the first 5 points padded with the first
    feeding = torch.cat([point_logits, f_se], 1)
    slots: dict[tuple, list[int]] = {}
    for i, p in enumerate(pts):
        v = [int(t) for t in torch.floor((p[:3] - torch.tensor(GRID.origin, dtype=torch.float64)) / GRID.voxel_size)]
        if all(0 <= a < b for a, b in zip(v, GRID.shape)) and v[2] + 1 < GRID.shape[2]:
            slots.setdefault((v[0], v[1], v[2] + 1), []).append(i)
    dense = torch.zeros(1, K - 1 + M, *GRID.shape, dtype=torch.float64)
    for v, rows in slots.items():
        first5 = rows[:5] + [rows[0]] * (5 - len(rows[:5]))
        dense[0, :, v[0], v[1], v[2]] = feeding[first5].mean(0)
    d = "complet_head.Decoder."

    def c3(name, h, stride=1, dilation=1):
        w = r[f"{d}{name}.0.weight"]
        out = F.conv3d(h, w, r[f"{d}{name}.0.bias"], stride, dilation * (w.shape[-1] // 2), dilation)
        return torch.relu(torch_bn(out, f"{d}{name}.1", 4))

    h = c3("b1_conv1", dense, 2)
    h = c3("b1_conv3", c3("b1_conv2", h)) + c3("b1_res", h)
    h = c3("b2_conv2", c3("b2_conv1", h)) + c3("b2_res", h)
    b3 = c3("b3_conv1", h)
    b3 = b3 + c3("b3_conv2", b3)
    b4 = c3("b4_conv1", b3, dilation=2)
    b4 = b4 + c3("b4_conv2", b4, dilation=2)
    b5 = c3("b5_conv1", b4, dilation=2)
    b5 = b5 + c3("b5_conv2", b5, dilation=2)
    coarse = F.conv3d(c3("pre_conv1", torch.cat([b3, b4, b5], 1)), r[d + "pre_conv2.0.weight"],
                      r[d + "pre_conv2.0.bias"])[0]
    # the interaction: supports = pooled voxels with F_SE, queries = non-zero coarse voxels, exact 8 nearest
    i = "complet_head.interaction_module."
    origin = torch.tensor(GRID.origin, dtype=torch.float64)
    sup = [v for v in sorted(slots) if dense[0, K - 1:, v[0], v[1], v[2]].abs().sum() > 0]
    qs = [tuple(q) for q in (coarse.abs().sum(0) > 0).nonzero().tolist()]
    fused = torch.zeros_like(coarse)
    for q in qs:
        q_xyz = (torch.tensor(q, dtype=torch.float64) + 0.5) * 2 * GRID.voxel_size + origin
        near = sorted(range(len(sup)), key=lambda j: (sum((2 * a + 1 - (4 * b + 2)) ** 2 for a, b in zip(sup[j], q)),
                                                      j))[:8]
        acc = torch.zeros(M, dtype=torch.float64)
        for j in near:
            s_xyz = (torch.tensor(sup[j], dtype=torch.float64) + 0.5) * GRID.voxel_size + origin
            rel = torch.cat([s_xyz - q_xyz, q_xyz, s_xyz, (s_xyz - q_xyz).norm()[None]])
            w = F.leaky_relu(torch_bn(r[i + "relation_w.conv.weight"][:, :, 0] @ rel, i + "relation_w.bn.bn"), 0.2)
            acc = acc + w * dense[0, K - 1:, sup[j][0], sup[j][1], sup[j][2]]
        both = torch.cat([acc / len(near), coarse[:, q[0], q[1], q[2]]])
        fused[:, q[0], q[1], q[2]] = F.leaky_relu(torch_bn(r[i + "fuse_mlps.fc.weight"] @ both, i + "fuse_mlps.bn.bn"),
                                                  0.2)
    u = "complet_head.upsample."
    up = torch.relu(torch_bn(F.conv3d(fused[None], r[u + "0.weight"], r[u + "0.bias"]), u + "1", 4))[0]
    logits = torch.zeros(K, *GRID.shape, dtype=torch.float64)
    for a, b, c in product(range(2), repeat=3):  # PixelShuffle3D: channel 8 k + 4 a + 2 b + c to (2x + a, 2y + b, 2z + c)
        logits[:, a::2, b::2, c::2] = up[4 * a + 2 * b + c::8]
    return point_logits, logits[None]


def test_a_release_checkpoint_loads_with_every_key_accounted_for_and_gives_the_releases_logits(tmp_path,
                                                                                                 device) -> None:
    from distilkit.weights import load_weights
    from distilkit.errors import DataError
    from distilkit_adapters.js3cnet.adapter import JS3CNetAdapter
    from distilkit_adapters.js3cnet.paper import JS3CNetPaper

    torch.manual_seed(0)
    model = JS3CNetAdapter.__new__(JS3CNetAdapter)  # the adapter's loading path around a network on GRID
    torch.nn.Module.__init__(model)
    model.net = JS3CNetPaper(K, seg_voxel=SEG_VOXEL)
    release = release_file(seed=4)
    assert sum(v.numel() for k, v in release.items() if not k.endswith(("running_mean", "running_var", "tracked"))) \
        == pytest.approx(4.84e6, rel=2e-3)  # the 18.5 MB file's parameters
    torch.save(release, tmp_path / "model_segiou_0.6327_compltiou_0.2350_epoch79.pth")
    weights = JS3CNetAdapter.read_weights(str(tmp_path / "model_segiou_0.6327_compltiou_0.2350_epoch79.pth"))
    left = load_weights(model, weights, True, "release")
    assert sorted(left) == ["ignored: complet_sigmas_sq (the uncertainty loss's weight)",
                            "ignored: seg_sigmas_sq (the uncertainty loss's weight)",
                            "ignored: voxelpool.* (unused with pooling_type: mean)"]
    model = model.double().eval().to(device)
    pts = points()
    with torch.no_grad():
        out = model.net(pts.to(device), torch.zeros(len(pts), dtype=torch.long, device=device), 1, GRID)
        out = {k: out[k].cpu() for k in ("point_logits", "logits")}
        model = model.cpu()
        want_points, want = reference(release, pts)
    assert torch.allclose(out["point_logits"], want_points, rtol=1e-9, atol=1e-9)
    assert int((want.abs().sum(1) > 0).sum()) > 100 and (want >= 0).all()  # the final ReLU
    assert torch.allclose(out["logits"], want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))
    # a key missing from the file is named as the model calls it and as the file spells it
    del release["seg_head.sparseModel.2.2.1.1.weight"]
    torch.save(release, tmp_path / "short.pth")
    with pytest.raises(DataError, match=r"1 missing: net\.seg_head\.sparseModel\.2\.2\.1\.1\.weight \(in the file: "
                                        r"seg_head\.sparseModel\.2\.2\.1\.1\.weight\)"):
        load_weights(model, JS3CNetAdapter.read_weights(str(tmp_path / "short.pth")), True, "short.pth")


def test_the_k_nearest_supports_are_exact_with_ties_to_the_lower_index() -> None:
    from distilkit_adapters.js3cnet.paper import grid_knn

    g = torch.Generator().manual_seed(5)
    support = torch.unique(torch.randint(0, 12, (150, 3), generator=g), dim=0) * 2 + 1  # centres, half-voxel units
    query = torch.unique(torch.randint(0, 6, (60, 3), generator=g), dim=0) * 4 + 2
    got = grid_knn(query, support, 8)
    for qi, q in enumerate(query.tolist()):
        d2 = [sum((a - b) ** 2 for a, b in zip(s, q)) for s in support.tolist()]
        assert got[qi].tolist() == sorted(range(len(d2)), key=lambda j: (d2[j], j))[:8]
    lone = grid_knn(query[:3], support[:1], 8)  # fewer supports than k: all of them
    assert lone.shape == (3, 1) and not lone.any()
