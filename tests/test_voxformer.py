"""The VoxFormer-style models' numerics against naive per-element implementations (float64, small sizes): projection
into cameras and lifting back, deformable cross-attention (bilinear sampling written out by hand), pooled occupancy,
the stage-1 losses and metric, and the adapters' proposals."""

from __future__ import annotations

import math

import pytest
import torch

from distilkit.data.batch import Batch
from distilkit.data.camera import intrinsics, lidar_to_camera
from distilkit.data.info import ClassTable, DataInfo
from distilkit.data.params import CameraParams
from distilkit.geometry.voxel import pool_occupancy
from distilkit.losses import depth_l1, occupancy_ce
from distilkit.structures import VoxelGrid
from distilkit_adapters.voxformer.adapter import VoxFormerAdapter, VoxFormerParams
from distilkit_adapters.voxformer.attention import DeformableCrossAttention, project
from distilkit_adapters.voxformer.proposal import lift, occupancy_counts

CAM = CameraParams(height=12, width=40)


def calibration(frames: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    k = torch.tensor(intrinsics(CAM), dtype=torch.float64).expand(frames, 3, 3)
    t = torch.stack([torch.tensor(lidar_to_camera(3 * f, 1.0), dtype=torch.float64) for f in range(frames)])
    return k, t


def test_projection_equals_the_pinhole_model_point_by_point() -> None:
    torch.manual_seed(0)
    points = torch.rand(50, 3, dtype=torch.float64) * torch.tensor([40.0, 30.0, 4.0]) - torch.tensor([5.0, 15.0, 2.0])
    k, t = calibration()
    pix, seen = project(points, k.expand(50, 2, 3, 3), t.expand(50, 2, 4, 4), (12, 40))
    for n in range(50):
        for f in range(2):
            cam = t[f] @ torch.cat([points[n], torch.ones(1, dtype=torch.float64)])
            u = (k[f, 0, 0] * cam[0] + k[f, 0, 2] * cam[2]) / cam[2]
            v = (k[f, 1, 1] * cam[1] + k[f, 1, 2] * cam[2]) / cam[2]
            inside = bool(cam[2] > 1e-5 and 0 <= u < 40 and 0 <= v < 12)
            assert bool(seen[n, f]) == inside
            if inside:
                assert torch.allclose(pix[n, f], torch.stack([u, v]))
    assert seen.any() and not seen.all()


def test_lifting_a_depth_map_inverts_the_projection() -> None:
    k, t = calibration(1)
    depth = torch.rand(1, 12, 40, dtype=torch.float64) * 30 + 1
    depth[0, 0, :5] = 0  # sky
    points, valid = lift(depth, k, t)
    pix, seen = project(points[0], k.expand(480, 1, 3, 3), t.expand(480, 1, 4, 4), (12, 40))
    v, u = torch.meshgrid(torch.arange(12, dtype=torch.float64) + 0.5, torch.arange(40, dtype=torch.float64) + 0.5,
                          indexing="ij")
    expect = torch.stack([u, v], -1).reshape(-1, 2)
    assert torch.allclose(pix[valid[0], 0], expect[valid[0]]) and seen[valid[0]].all() and int((~valid).sum()) == 5
    grid = VoxelGrid((0.0, -16.0, -2.0), (8, 8, 2), 4.0)
    counts = occupancy_counts(points, valid, grid)
    idx, inside = grid.index(points[0][valid[0]])
    naive = torch.zeros(2, 8, 8, dtype=torch.float64)
    for (x, y, z) in idx[inside].tolist():
        naive[z, x, y] += 1
    assert torch.allclose(counts[0], naive.log1p())


def bilinear(feature: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """Bilinear sample of (C, h, w) at pixel coordinates (x, y) with pixel centres at +0.5, zero outside."""
    c, h, w = feature.shape
    x0, y0 = math.floor(x - 0.5), math.floor(y - 0.5)
    out = torch.zeros(c, dtype=feature.dtype)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            wx = 1 - abs(x - 0.5 - xi)
            wy = 1 - abs(y - 0.5 - yi)
            if 0 <= xi < w and 0 <= yi < h:
                out = out + wx * wy * feature[:, yi, xi]
    return out


def naive_attention(layer: DeformableCrossAttention, query, pos, batch_index, pixels, seen, features, size):
    n, c = query.shape
    hd, t, p = layer.heads, layer.frames, layer.points
    b, _, _, fh, fw = features.shape
    out = torch.zeros(n, c, dtype=query.dtype)
    for i in range(n):
        q = query[i] + pos[i]
        offsets = layer.offsets(q).view(hd, t, p, 2)
        weights = layer.weights(q).view(hd, t, p).softmax(-1)
        frames = [f for f in range(t) if seen[i, f]]
        read = torch.zeros(hd, c // hd, dtype=query.dtype)
        for f in frames:
            value = layer.value(features[batch_index[i], f].permute(1, 2, 0)).permute(2, 0, 1)  # (C, h, w)
            for h in range(hd):
                for j in range(p):
                    x = pixels[i, f, 0] * fw / size[1] + offsets[h, f, j, 0]
                    y = pixels[i, f, 1] * fh / size[0] + offsets[h, f, j, 1]
                    read[h] += weights[h, f, j] * bilinear(value[h * c // hd:(h + 1) * c // hd], float(x.detach()), float(y.detach()))
        update = layer.out(read.reshape(c) / max(len(frames), 1)) if frames else torch.zeros(c, dtype=query.dtype)
        x = layer.norm1(query[i] + update)
        out[i] = layer.norm2(x + layer.mlp(x))
    return out


def attention_case(seed: int = 0, hw: tuple[int, int] = (3, 10)):
    """A layer and its inputs; ``hw``: the feature maps' height and width (the image is 12 x 40 pixels either way)."""
    torch.manual_seed(seed)
    layer = DeformableCrossAttention(channels=8, heads=2, points=3, frames=2).double()
    with torch.no_grad():
        layer.offsets.weight.normal_(0, 0.5)
    n = 7
    query, pos = torch.randn(n, 8, dtype=torch.float64), torch.randn(n, 8, dtype=torch.float64)
    batch_index = torch.tensor([0, 0, 1, 1, 1, 0, 1])
    pixels = torch.rand(n, 2, 2, dtype=torch.float64) * torch.tensor([40.0, 12.0], dtype=torch.float64)
    seen = torch.tensor([[1, 1], [1, 0], [0, 1], [1, 1], [0, 0], [1, 1], [1, 0]], dtype=torch.bool)
    features = torch.randn(2, 2, 8, *hw, dtype=torch.float64)
    return layer, query, pos, batch_index, pixels, seen, features, (12, 40)


def test_deformable_cross_attention_equals_a_naive_bilinear_reading() -> None:
    layer, query, pos, bi, pixels, seen, features, size = attention_case()
    fast = layer(query, pos, bi, pixels, seen, features, size)
    slow = naive_attention(layer, query, pos, bi, pixels, seen, features, size)
    assert torch.allclose(fast, slow, atol=1e-10)
    # a query seen in no frame only passes the residual path
    assert torch.allclose(fast[4], layer.norm2(layer.norm1(query[4]) + layer.mlp(layer.norm1(query[4]))))


def test_deformable_cross_attention_gradients() -> None:
    """gradcheck of queries and feature maps; 2 x 5 feature maps (a third of the numerical perturbations of 3 x 10)
    still put samples inside, on the border and outside of the maps."""
    layer, query, pos, bi, pixels, seen, features, size = attention_case(1, hw=(2, 5))
    query.requires_grad_(True)
    features.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q, f: layer(q, pos, bi, pixels, seen, f, size), (query, features),
                                    eps=1e-6, atol=1e-5)


def test_pool_occupancy_follows_the_block_rule() -> None:
    torch.manual_seed(0)
    target = torch.randint(0, 3, (2, 4, 4, 2)) * torch.randint(0, 2, (2, 4, 4, 2))
    target[0, :2, :2, :] = 255  # one block all ignored
    target[1, 2:, 2:, :] = 0  # one block all empty
    pooled = pool_occupancy(target, 2)
    for b in range(2):
        for x in range(2):
            for y in range(2):
                block = target[b, 2 * x:2 * x + 2, 2 * y:2 * y + 2, 0:2].flatten().tolist()
                want = 1 if any(v not in (0, 255) for v in block) else 0 if 0 in block else 255
                assert int(pooled[b, x, y, 0]) == want
    assert int(pooled[0, 0, 0, 0]) == 255 and int(pooled[1, 1, 1, 0]) == 0


def test_stage_one_losses_equal_their_formulas() -> None:
    torch.manual_seed(0)
    logits = torch.randn(2, 2, 2, 2, 1, dtype=torch.float64, requires_grad=True)
    target = torch.randint(0, 4, (2, 4, 4, 2))
    target[0, 0, 0, 0] = 255
    occ = pool_occupancy(target, 2)
    num = den = 0.0
    for idx in torch.cartesian_prod(*(torch.arange(s) for s in occ.shape)).tolist():
        y = int(occ[tuple(idx)])
        if y == 255:
            continue
        b, x, yy, z = idx
        w = (0.46, 0.54)[y]
        num = num - w * torch.log_softmax(logits[b, :, x, yy, z], 0)[y]
        den += w
    assert torch.allclose(occupancy_ce(logits, target), num / den)
    assert torch.autograd.gradcheck(lambda lg: occupancy_ce(lg, target), (logits,))

    pred, depth = torch.rand(1, 3, 4, dtype=torch.float64), torch.rand(1, 3, 4, dtype=torch.float64) * 5
    depth[0, 0] = 0
    assert torch.allclose(depth_l1(pred, depth), (pred - depth).abs()[0, 1:].mean())
    assert torch.allclose(depth_l1(pred, depth, sky_depth=80.0),
                          (pred - depth.masked_fill(depth == 0, 80.0)).abs().mean())


def test_the_adapter_proposes_the_ground_truth_geometry_or_a_stage_one_models() -> None:
    grid = VoxelGrid((0.0, -25.6, -2.0), (8, 8, 4), 6.4)
    info = DataInfo(grid, ClassTable.semantickitti(), frozenset(), ())
    torch.manual_seed(0)
    target = torch.randint(0, 20, (1, 8, 8, 4)) * (torch.rand(1, 8, 8, 4) < 0.2)
    k, t = calibration(1)
    inputs = {"image": torch.rand(1, 1, 3, 12, 40), "intrinsics": k.float()[None], "lidar_to_camera": t.float()[None]}
    batch = Batch(inputs, {"voxel_target": target}, {"size": 1})
    truth = VoxFormerAdapter(VoxFormerParams(geometry="ground-truth"), info)
    out = truth(batch)
    assert torch.equal(out["query_features"].coords, torch.nonzero(pool_occupancy(target, 2) == 1))
    assert out["logits"].shape == (1, 20, 8, 8, 4) and out["image_features"].shape[:2] == (1, 16)
    proposed = VoxFormerAdapter(VoxFormerParams(), info)
    scores = torch.zeros(1, 2, 4, 4, 2)
    scores[0, 1, 1, 2, 0] = 1.0
    out = proposed(batch.with_inputs(proposal=scores))
    assert out["query_features"].coords.tolist() == [[0, 1, 2, 0]]
    with pytest.raises(ValueError, match="proposal"):
        proposed(batch.with_inputs(proposal=torch.zeros(1, 2, 8, 8, 4)))
