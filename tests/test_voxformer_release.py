"""VoxFormer at ``size: paper`` computes what its release computes: the deformable attention modules against naive
float64 references of the release's formulas (sampling point by point with explicit bilinear / trilinear corners,
``num_bev_queue`` = 2, the camera re-batching of the cross-attention), gradients; and a file in the released
VoxFormer-S layout (mmdet's ``{"state_dict": ...}``: ``img_backbone.*``, ``img_neck.*``, ``pts_bbox_head.*``, its
FFN 256 wide, ``level_embeds`` and ``cams_embeds`` in both transformers) loads with every key used or reported, and
the network's logits equal an independent float64 reference of the release's head (point sampling, 3 cross- and 2
self-attention layers, the header's align_corners=True upsampling) on the image encoder's features."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from distilkit.structures import VoxelGrid
from distilkit_adapters.voxformer.deformable import DeformCrossAttention, DeformSelfAttention, plane_shape
from distilkit_adapters.voxformer.resnet import Bottleneck

C, HEADS, POINTS, K = 128, 8, 8, 20


def corners(values: torch.Tensor, where: list[float]) -> torch.Tensor:
    """``values`` (C, *cells) at ``where`` (cell coordinates, centres at integers), multilinear, zero outside."""
    base = [math.floor(w) for w in where]
    out = torch.zeros(values.shape[0], dtype=values.dtype)
    for corner in itertools.product((0, 1), repeat=len(where)):
        idx = [b + c for b, c in zip(base, corner)]
        weight = 1.0
        for w, i in zip(where, idx):
            weight *= 1 - abs(w - i)
        if all(0 <= i < s for i, s in zip(idx, values.shape[1:])):
            out = out + weight * values[(slice(None), *idx)]
    return out


def read(values: torch.Tensor, cells: tuple[int, ...], loc: list[float]) -> torch.Tensor:
    """The release's sampling: location (w, h[, z]) in 0..1 -> cell (h, w[, z]) at location x size - 0.5."""
    order = [loc[1], loc[0], *loc[2:]]
    return corners(values, [o * s - 0.5 for o, s in zip(order, cells)])


def linear(r: dict, name: str, x: torch.Tensor) -> torch.Tensor:
    return x @ r[name + ".weight"].t() + r[name + ".bias"]


def layer_norm(r: dict, name: str, x: torch.Tensor) -> torch.Tensor:
    return F.layer_norm(x, x.shape[-1:], r[name + ".weight"], r[name + ".bias"])


def finish(r: dict, p: str, x: torch.Tensor) -> torch.Tensor:
    """norm, FFN (+ its input), norm."""
    x = layer_norm(r, p + "norms.0", x)
    x = x + linear(r, p + "ffns.0.layers.1", torch.relu(linear(r, p + "ffns.0.layers.0.0", x)))
    return layer_norm(r, p + "norms.1", x)


def naive_self(r: dict, p: str, x: torch.Tensor, pos: torch.Tensor, volume: tuple[int, int, int],
               space: str) -> torch.Tensor:
    """The release's DeformSelfAttention (num_bev_queue 2) query by query, point by point, + its residual."""
    n = len(x)
    cells = plane_shape(n) if space == "plane" else volume
    d = len(cells)
    value = linear(r, p + "value_proj", x)  # (N, C)
    grid = value.t().reshape(C, *cells)
    out = torch.zeros_like(x)
    for i in range(n):
        q = torch.cat([x[i], x[i] + pos[i]])
        off = linear(r, p + "sampling_offsets", q).view(HEADS, 2, POINTS, d)
        w = linear(r, p + "attention_weights", q).view(HEADS, 2, POINTS).softmax(-1)
        cell = [int(c) for c in torch.unravel_index(torch.tensor(i), cells)]
        ref = [(cell[1] + 0.5) / cells[1], (cell[0] + 0.5) / cells[0], *[(c + 0.5) / s for c, s in
                                                                        zip(cell[2:], cells[2:])]]
        norm = [cells[1], cells[0], *cells[2:]]
        heads = []
        for h in range(HEADS):
            acc = torch.zeros(C // HEADS, dtype=x.dtype)
            for queue in range(2):
                for k in range(POINTS):
                    loc = [float(ref[a] + off[h, queue, k, a] / norm[a]) for a in range(d)]
                    acc = acc + 0.5 * w[h, queue, k] * read(grid[h * (C // HEADS):(h + 1) * (C // HEADS)], cells, loc)
            heads.append(acc)
        out[i] = linear(r, p + "output_proj", torch.cat(heads)) + x[i]
    return out


def naive_cross(r: dict, p: str, x: torch.Tensor, values: torch.Tensor, ref: torch.Tensor, seen: torch.Tensor,
                shape: tuple[int, int]) -> torch.Tensor:
    """The release's DeformCrossAttention: per image its seen queries, MSDeformableAttention3D point by point, the
    reads summed and divided by the images that see the query, output_proj on every query, + the query."""
    d = p + "deformable_attention."
    slots = torch.zeros_like(x)
    for t in range(len(values)):
        grid = linear(r, d + "value_proj", values[t]).t().reshape(C, *shape)
        for i in seen[t].nonzero().squeeze(1).tolist():
            off = linear(r, d + "sampling_offsets", x[i]).view(HEADS, POINTS, 2)
            w = linear(r, d + "attention_weights", x[i]).view(HEADS, POINTS).softmax(-1)
            heads = []
            for h in range(HEADS):
                acc = torch.zeros(C // HEADS, dtype=x.dtype)
                for k in range(POINTS):
                    loc = [float(ref[t, i, 0] + off[h, k, 0] / shape[1]), float(ref[t, i, 1] + off[h, k, 1] / shape[0])]
                    acc = acc + w[h, k] * read(grid[h * (C // HEADS):(h + 1) * (C // HEADS)], shape, loc)
                heads.append(acc)
            slots[i] += torch.cat(heads)
    count = seen.sum(0).clamp_min(1).to(x.dtype)[:, None]
    return linear(r, p + "output_proj", slots / count) + x


def randomise(module: nn.Module, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for name, v in module.state_dict().items():
        if v.is_floating_point():
            scale = 0.5 if "sampling_offsets" in name else 0.3
            v.copy_(torch.randn(v.shape, generator=g, dtype=v.dtype) * scale + (1.0 if "norm" in name and
                                                                                 name.endswith("weight") else 0.0))


@pytest.mark.parametrize("space,volume", [("plane", (2, 3, 2)), ("3d", (3, 2, 2))])
def test_self_attention_equals_the_naive_release_formula_with_gradients(space, volume) -> None:
    layer = DeformSelfAttention(C, HEADS, POINTS, space).double().eval()
    randomise(layer, 1)
    n = volume[0] * volume[1] * volume[2]
    g = torch.Generator().manual_seed(2)
    x = torch.randn(1, n, C, generator=g, dtype=torch.float64)
    pos = torch.randn(n, C, generator=g, dtype=torch.float64)
    r = {k: v for k, v in layer.state_dict().items()}
    assert torch.allclose(layer(x, pos, volume)[0], naive_self(r, "", x[0], pos, volume, space), atol=1e-10)
    small = DeformSelfAttention(8, 2, 2, space).double().eval()
    randomise(small, 3)
    xs = torch.randn(1, n, 8, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: small(v, pos[:, :8], volume), (xs,))


def test_cross_attention_equals_the_naive_release_formula() -> None:
    attn = DeformCrossAttention(C, HEADS, POINTS).double().eval()
    randomise(attn, 4)
    g = torch.Generator().manual_seed(5)
    shape = (3, 5)
    x = torch.randn(6, C, generator=g, dtype=torch.float64)
    values = torch.randn(2, 15, C, generator=g, dtype=torch.float64)  # two images (VoxFormer-T's frames)
    ref = torch.rand(2, 6, 2, generator=g, dtype=torch.float64)
    seen = torch.tensor([[1, 1, 0, 1, 0, 0], [1, 0, 1, 1, 0, 1]], dtype=torch.bool)  # query 4: seen by none
    r = {k: v for k, v in attn.state_dict().items()}
    assert torch.allclose(attn(x, values, ref, seen, shape), naive_cross(r, "", x, values, ref, seen, shape),
                          atol=1e-10)


GRID = VoxelGrid.semantickitti(16)  # 16 x 16 x 2 voxels of 3.2 m; queries 8 x 8 x 1
IMAGE = (64, 192)


def head_shapes(n: int, frames: int) -> dict[str, tuple[int, ...]]:
    """``pts_bbox_head.*`` and ``img_neck.*`` of the released VoxFormer-S / -T (voxformer-S.py: 128 channels, 8
    heads and points, one level, FFN 256 wide, 3 cross- and 2 self-attention layers)."""
    out = {"img_neck.lateral_convs.0.conv.weight": (C, 1024, 1, 1), "img_neck.lateral_convs.0.conv.bias": (C,),
           "img_neck.fpn_convs.0.conv.weight": (C, C, 3, 3), "img_neck.fpn_convs.0.conv.bias": (C,)}
    h = "pts_bbox_head."
    out |= {h + "bev_embed.weight": (n, C), h + "mask_embed.weight": (1, C),
            h + "positional_encoding.row_embed.weight": (512, C // 2),
            h + "positional_encoding.col_embed.weight": (512, C // 2),
            h + "header.mlp_head.0.weight": (C,), h + "header.mlp_head.0.bias": (C,),
            h + "header.mlp_head.1.weight": (K, C), h + "header.mlp_head.1.bias": (K,)}

    def lin(name: str, cin: int, cout: int) -> dict[str, tuple[int, ...]]:
        return {name + ".weight": (cout, cin), name + ".bias": (cout,)}

    def common(p: str) -> dict[str, tuple[int, ...]]:
        return {**lin(p + "ffns.0.layers.0.0", C, 2 * C), **lin(p + "ffns.0.layers.1", 2 * C, C),
                p + "norms.0.weight": (C,), p + "norms.0.bias": (C,), p + "norms.1.weight": (C,),
                p + "norms.1.bias": (C,)}

    for t in ("cross", "self"):
        out |= {f"{h}{t}_transformer.level_embeds": (4, C), f"{h}{t}_transformer.cams_embeds": (frames, C)}
    for i in range(3):
        p = f"{h}cross_transformer.encoder.layers.{i}."
        d = p + "attentions.0.deformable_attention."
        out |= {**lin(d + "sampling_offsets", C, HEADS * POINTS * 2), **lin(d + "attention_weights", C, HEADS * POINTS),
                **lin(d + "value_proj", C, C), **lin(p + "attentions.0.output_proj", C, C), **common(p)}
    for i in range(2):
        p = f"{h}self_transformer.encoder.layers.{i}."
        a = p + "attentions.0."
        out |= {**lin(a + "sampling_offsets", 2 * C, 2 * HEADS * POINTS * 2),  # 256 -> 256
                **lin(a + "attention_weights", 2 * C, 2 * HEADS * POINTS), **lin(a + "value_proj", C, C),
                **lin(a + "output_proj", C, C), **common(p)}
    return out


def release_file(model: nn.Module, frames: int, seed: int) -> dict[str, torch.Tensor]:
    """A VoxFormer checkpoint's state dict: mmdet's ResNet-50 (torchvision's names, the fourth stage too) and the
    head's keys above, random values of a sensible scale."""
    g = torch.Generator().manual_seed(seed)
    n = model.net.query_grid.shape[0] * model.net.query_grid.shape[1] * model.net.query_grid.shape[2]
    shapes = head_shapes(n, frames)
    backbone = {f"img_backbone.{k}": tuple(v.shape) for k, v in model.net.img_backbone.state_dict().items()}
    layer4 = nn.Sequential(Bottleneck(1024, 512, 2), Bottleneck(2048, 512, 1), Bottleneck(2048, 512, 1))
    backbone |= {f"img_backbone.layer4.{k}": tuple(v.shape) for k, v in layer4.state_dict().items()}
    out = {}
    for key, shape in {**backbone, **shapes}.items():
        if key.endswith("num_batches_tracked"):
            out[key] = torch.tensor(5)
        elif key.endswith("running_var"):
            out[key] = 1 + 0.2 * torch.rand(shape, generator=g)
        elif key.endswith(("running_mean", "bias")):
            out[key] = 0.1 * torch.randn(shape, generator=g)
        elif "norm" in key or "mlp_head.0" in key or ".bn" in key:
            out[key] = 1 + 0.1 * torch.randn(shape, generator=g)
        else:
            fan_in = int(torch.tensor(shape[1:]).prod()) if len(shape) > 1 else 1
            scale = 0.5 if "sampling_offsets" in key else (1.0 if "embed" in key else (1.0 / fan_in) ** 0.5)
            out[key] = scale * torch.randn(shape, generator=g)
    return out


def reference_head(r: dict, feats: torch.Tensor, to_image: torch.Tensor, proposed: torch.Tensor,
                   space: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The release's ``VoxFormerHead`` in float64 from its state dict: (queries after cross-attention, logits)."""
    h = "pts_bbox_head."
    qg = GRID.coarsen(2)
    X, Y, Z = qg.shape
    n = X * Y * Z
    # point_sampling: ref_3d in 0..1 of the range, to metres, lidar2img, depth > 1e-5, strictly inside
    idx = torch.tensor(list(itertools.product(range(X), range(Y), range(Z))), dtype=torch.float64)
    ref3d = (idx + 0.5) / torch.tensor(qg.shape, dtype=torch.float64)
    lo = torch.tensor(qg.origin, dtype=torch.float64)
    metres = ref3d * (torch.tensor(qg.shape, dtype=torch.float64) * qg.voxel_size) + lo
    cam = torch.einsum("tij,nj->tni", to_image, torch.cat([metres, torch.ones(n, 1, dtype=torch.float64)], 1))
    seen = cam[..., 2] > 1e-5
    uv = cam[..., :2] / torch.maximum(cam[..., 2:3], torch.full_like(cam[..., 2:3], 1e-5))
    uv = uv / torch.tensor([IMAGE[1], IMAGE[0]], dtype=torch.float64)
    seen = seen & (uv[..., 0] > 0) & (uv[..., 0] < 1) & (uv[..., 1] > 0) & (uv[..., 1] < 1)
    rows = proposed.nonzero().squeeze(1)
    shape = tuple(feats.shape[-2:])
    values = feats.flatten(2).transpose(1, 2) + r[h + "cross_transformer.cams_embeds"][:, None] + \
        r[h + "cross_transformer.level_embeds"][None, 0:1]
    x = r[h + "bev_embed.weight"][rows]
    for i in range(3):
        p = f"{h}cross_transformer.encoder.layers.{i}."
        x = finish(r, p, naive_cross(r, p + "attentions.0.", x, values, uv[:, rows], seen[:, rows], shape))
    volume = r[h + "mask_embed.weight"].repeat(n, 1)
    volume[rows] = x
    prow, pcol = plane_shape(n)
    cell = torch.arange(n)
    pos = torch.cat([r[h + "positional_encoding.col_embed.weight"][cell % pcol],
                     r[h + "positional_encoding.row_embed.weight"][cell // pcol]], 1)
    for i in range(2):
        p = f"{h}self_transformer.encoder.layers.{i}."
        volume = finish(r, p, naive_self(r, p + "attentions.0.", volume, pos, qg.shape, space))
    up = F.interpolate(volume.t().reshape(1, C, X, Y, Z), scale_factor=2, mode="trilinear", align_corners=True)
    logits = linear(r, h + "header.mlp_head.1", layer_norm(r, h + "header.mlp_head.0", up.permute(0, 2, 3, 4, 1)))
    return x, logits.permute(0, 4, 1, 2, 3)


@pytest.mark.parametrize("space", ["plane", "3d"])
def test_a_released_checkpoint_loads_with_every_key_accounted_for_and_gives_the_releases_logits(space, tmp_path,
                                                                                                 device) -> None:
    from distilkit.data.camera import intrinsics, lidar_to_camera
    from distilkit.data.info import DataInfo
    from distilkit.data.params import CameraParams
    from distilkit.weights import load_weights
    from distilkit_adapters.voxformer.adapter import VoxFormerAdapter, VoxFormerParams

    torch.manual_seed(0)
    info = DataInfo(GRID, fields=frozenset({"image", "intrinsics", "lidar_to_camera", "voxel_target"}))
    model = VoxFormerAdapter(VoxFormerParams(size="paper", geometry="ground-truth",
                                             mixing=f"deformable-{space}"), info)
    release = release_file(model, 1, seed=6)
    assert release["pts_bbox_head.self_transformer.encoder.layers.0.attentions.0.sampling_offsets.weight"].shape \
        == (256, 256)  # voxformer-S.py's 2-D DeformSelfAttention
    if space == "3d":  # the deform3D configs' layer: 3 offsets per point
        for i in range(2):
            p = f"pts_bbox_head.self_transformer.encoder.layers.{i}.attentions.0.sampling_offsets."
            release[p + "weight"] = 0.5 * torch.randn(384, 256)
            release[p + "bias"] = 0.1 * torch.randn(384)
    torch.save({"meta": {"epoch": 20}, "state_dict": release}, tmp_path / "voxformer-s.pth")
    weights = VoxFormerAdapter.read_weights(str(tmp_path / "voxformer-s.pth"))
    left = load_weights(model, weights, True, "release")
    assert left == ["ignored: img_backbone.layer4.* (the fourth stage: out_indices=(2,) reads the third)",
                    "ignored: pts_bbox_head.self_transformer.level_embeds (the self-attention reads no image)",
                    "ignored: pts_bbox_head.self_transformer.cams_embeds (the self-attention reads no image)"]
    model = model.double().eval()
    cam = CameraParams(height=IMAGE[0], width=IMAGE[1])
    k = torch.tensor(intrinsics(cam), dtype=torch.float64).view(1, 1, 3, 3)
    ext = torch.tensor(lidar_to_camera(0, 1.0), dtype=torch.float64).view(1, 1, 4, 4)
    images = torch.rand(1, 1, 3, *IMAGE, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    proposed = torch.zeros(8, 8, 1, dtype=torch.bool)
    proposed[1:7, 2:6] = True
    with torch.no_grad():
        model = model.to(device)  # the network on the device of --device, the reference on the CPU
        feats, queries, logits = model.net(images.to(device), k.to(device), ext.to(device), proposed[None].to(device))
        model, feats, queries, logits = model.cpu(), feats.cpu(), queries.to("cpu"), logits.cpu()
        pad = torch.eye(4, dtype=torch.float64)
        pad[:3, :3] = k[0, 0]
        r = {key: v.double() for key, v in release.items()}
        want_q, want = reference_head(r, feats[0], (pad @ ext[0, 0])[None], proposed.reshape(-1), space)
    head = model.net.pts_bbox_head
    uv, seen = head.references((pad @ ext[0, 0])[None], IMAGE)
    assert 0 < int(seen[0][proposed.reshape(-1)].sum()) < int(proposed.sum())  # some proposed queries unseen
    assert torch.allclose(queries.feats, want_q, rtol=1e-9, atol=1e-9)
    assert torch.allclose(logits, want, rtol=1e-9, atol=1e-9)
