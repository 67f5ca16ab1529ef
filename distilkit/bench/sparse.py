"""``distilkit bench sparse``: a Cylinder3D-sized submanifold 3x3x3 layer (64 -> 64 channels) forward + backward at a
real scan's occupancy of the 256 x 256 x 32 grid (five fused HDL-64E-sized scans of the synthetic streets, about as
many active voxels as Cylinder3D's input), against the arithmetic it does and against dense ``conv3d`` on the same
grid (its value restricted to the active sites: the two must agree).

The arithmetic: each neighbour pair costs 2 C_in C_out flops in the forward pass and twice that in the backward
(gradients of the features and of the weight), so GFLOP/s = 6 P C_in C_out / time. It is set beside this CPU's
single-precision GEMM rate (a 4096 x 4096 ``torch.mm``), measured in the same run. On CUDA the same layer is timed
on each library backend present (spconv 2.x, spconv-Triton: :mod:`distilkit.sparse.backend`) against the torch
path, each with its GFLOP/s beside the GPU's GEMM rate.
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch
from torch import Tensor

from distilkit.bench.base import Case, register, scratch_dir
from distilkit.sparse.form import form


def scan_occupancy(quick: bool) -> Tensor:
    """(N, 4) int32 active voxels (batch 0) of five fused synthetic HDL-64E scans on the 256 x 256 x 32 grid (quick:
    32 beams, one scan)."""
    from distilkit.data.kitti_folder import SemanticKittiDataset
    from distilkit.data.export import export_kitti
    from distilkit.data.params import SemanticKittiParams, SyntheticParams
    from distilkit.structures import VoxelGrid

    root = scratch_dir("sparse-")
    beams, steps, frames = (32, 1024, 1) if quick else (64, 2048, 5)
    export_kitti(root, SyntheticParams(beams=beams, azimuth_steps=steps, gt_frames=4), ["08"], frames=6, stride=5)
    sample = SemanticKittiDataset(SemanticKittiParams(root=str(root), val=["08"], input_frames=frames), "val")[0]
    grid = VoxelGrid.semantickitti(1)
    idx, inside = grid.index(torch.from_numpy(sample["points"][:, :3]))
    voxels = torch.unique(idx[inside], dim=0)
    return torch.cat([torch.zeros(len(voxels), 1, dtype=torch.long), voxels], dim=1).int()


def sgemm_gflops(device: torch.device, n: int = 4096, repeat: int = 5) -> float:
    """This device's single-precision GEMM rate: the median of ``repeat`` n x n products."""
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)
    torch.mm(a, b)
    times = []
    for _ in range(repeat):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t0 = time.perf_counter()
        torch.mm(a, b)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(time.perf_counter() - t0)
    return 2 * n ** 3 / sorted(times)[len(times) // 2] / 1e9


@register("sparse")
def sparse_cases(device: torch.device, quick: bool) -> list[Case]:
    from distilkit.sparse import SparseConvTensor, SubMConv3d

    channels = 16 if quick else 64
    shape = (128, 128, 16) if quick else (256, 256, 32)  # quick: the sites inside a smaller grid
    indices = scan_occupancy(quick)
    indices = indices[(indices[:, 1:] < torch.tensor(shape)).all(dim=1)].to(device)
    g = torch.Generator().manual_seed(0)
    feats = torch.randn(len(indices), channels, generator=g).to(device).requires_grad_()
    conv = SubMConv3d(channels, channels, 3, bias=False, indice_key="bench").to(device)
    weight = conv.weight
    checks = []
    for _ in range(5):  # building a tensor checks its indices (bounds, duplicates): one sort, reused by the map
        t0 = time.perf_counter()
        x = SparseConvTensor(feats, indices, shape, 1)
        checks.append(time.perf_counter() - t0)
    checking = sorted(checks)[2]
    t0 = time.perf_counter()
    book = conv.rulebook(x)  # hashed once: a network's layers share it
    hashing = time.perf_counter() - t0

    def sparse() -> Tensor:
        return conv(x.derived(feats, indice_dict={"bench": book})).features.sum()

    idx = indices.long()
    mask = torch.zeros((1, 1, *shape), device=device)
    mask[0, 0, idx[:, 1], idx[:, 2], idx[:, 3]] = 1.0

    def dense() -> Tensor:
        grid = torch.zeros((1, *shape, channels), device=device, dtype=feats.dtype)
        grid = grid.index_put((idx[:, 0], idx[:, 1], idx[:, 2], idx[:, 3]), feats)
        out = torch.nn.functional.conv3d(grid.permute(0, 4, 1, 2, 3), weight.permute(0, 4, 1, 2, 3), padding=1)
        return (out * mask).sum()

    pairs = book.pairs
    gemm = sgemm_gflops(device)
    flops = 6 * pairs * channels * channels

    def note(row: dict[str, Any]) -> str:
        rate = flops / (row["fast_ms"] / 1000) / 1e9
        dense_rate = ""
        if "naive_ms" in row:
            dense_flops = 6 * shape[0] * shape[1] * shape[2] * 27 * channels * channels
            dense_rate = (f"; dense conv3d: {dense_flops / 1e9:,.0f} GFLOP in {row['naive_ms'] / 1000:.2f} s = "
                          f"{dense_flops / (row['naive_ms'] / 1000) / 1e9:.1f} GFLOP/s, the sparse layer "
                          f"{compared(row['fast_ms'], row['naive_ms'])} than dense conv3d")
        return (f"sparse: {len(indices):,} active voxels, {pairs:,} neighbour pairs ({pairs / len(indices):.1f} a "
                f"voxel; the neighbour map hashed once in {hashing * 1000:.0f} ms, shared by the layers of a network; "
                f"checking the indices when the tensor is built {checking * 1000:.1f} ms, "
                f"{checking / (row['fast_ms'] / 1000) * 100:.1f} % of one layer), "
                f"{flops / 1e9:.2f} GFLOP forward + backward in {row['fast_ms']:.0f} ms = {rate:.1f} "
                f"GFLOP/s; this {device.type}'s sgemm (4096^2): {gemm:.1f} GFLOP/s; ratio {rate / gemm:.2f}"
                + dense_rate)

    size = f"SubM 3x3x3 {channels}->{channels}, {len(indices):,} of {'x'.join(map(str, shape))} voxels"
    cases = [Case("sparse: SubMConv3d vs dense conv3d", size, on("torch", sparse), dense, [feats, weight],
                  note=note)]
    cases.append(Case("sparse: table vs loop form (torch path)", size, on("torch", sparse, "table"),
                      on("torch", sparse, "loop"), [feats, weight],
                      note=lambda row: f"table form ({form(device.type)} is this {device.type}'s default): "
                                       + note(row).split("; dense")[0]))
    for name in library_backends(device):  # the same layer on each library present, against the torch path
        cases.append(Case(f"sparse: {name} vs torch backend", size, on(name, sparse), on("torch", sparse),
                          [feats, weight], note=lambda row, name=name: f"{name}: " + note(row).split("; dense")[0]))
    return cases


def tiled(indices: Tensor, copies: int, shape: tuple[int, int, int]) -> tuple[Tensor, tuple[int, int, int]]:
    """``copies`` copies of a scan's (N, 4) voxels side by side along x and y in a grid that holds them (each voxel
    keeps its neighbourhood, so the pairs per voxel stay the scan's): (indices, the grid)."""
    side = math.ceil(math.sqrt(copies))
    rows = [indices[:, 1:] + torch.tensor([i % side * shape[0], i // side * shape[1], 0], device=indices.device,
                                          dtype=indices.dtype) for i in range(copies)]
    coords = torch.cat(rows)
    out = torch.cat([torch.zeros_like(coords[:, :1]), coords], dim=1)
    return out, (shape[0] * side, shape[1] * math.ceil(copies / side), shape[2])


@register("sparse-sizes")
def sparse_size_cases(device: torch.device, quick: bool) -> list[Case]:
    """The torch path's table form against each library present (spconv, spconv-Triton: the issue's goal is 1.5x of
    spconv) — or against the loop form where none is — for a SubM 3x3x3 layer at 20k-400k voxels (copies of the
    five-scan occupancy side by side) and 32, 64 and 128 channels; quick: one copy of the quick occupancy at 16 and
    32 channels."""
    from distilkit.sparse import SparseConvTensor, SubMConv3d

    base = scan_occupancy(quick)
    shape = (128, 128, 16) if quick else (256, 256, 32)
    base = base[(base[:, 1:] < torch.tensor(shape)).all(dim=1)]
    plan = [(1, 16), (1, 32)] if quick else [(c, ch) for c in (1, 4, 18) for ch in (32, 64, 128)]
    against = library_backends(device) or ["loop"]
    cases = []
    for copies, channels in plan:
        indices, grid = tiled(base, copies, shape)
        indices = indices.int().to(device)
        g = torch.Generator().manual_seed(copies * 1000 + channels)
        feats = torch.randn(len(indices), channels, generator=g).to(device).requires_grad_()
        conv = SubMConv3d(channels, channels, 3, bias=False, indice_key="bench").to(device)
        x = SparseConvTensor(feats, indices, grid, 1)
        book = conv.rulebook(x)

        def layer(conv: Any = conv, x: Any = x, feats: Tensor = feats, book: Any = book) -> Tensor:
            return conv(x.derived(feats, indice_dict={"bench": book})).features.sum()

        size = f"SubM 3x3x3 {channels}->{channels}, {len(indices):,} voxels, {book.pairs / len(indices):.1f} pairs each"
        for other in against:
            slow = on("torch", layer, "loop") if other == "loop" else on(other, layer)
            cases.append(Case(f"sparse: table vs {other}", size, on("torch", layer, "table"), slow,
                              [feats, conv.weight]))
    return cases


def compared(ms: float, other_ms: float) -> str:
    """How a time of ``ms`` compares with ``other_ms``: the ratio of the longer to the shorter (1 or more) and its
    direction in words, "2.5x faster" where ``ms`` is the shorter, "2.5x slower" where it is the longer."""
    if ms <= other_ms:
        return f"{other_ms / max(ms, 1e-12):.1f}x faster"
    return f"{ms / max(other_ms, 1e-12):.1f}x slower"


def library_backends(device: torch.device) -> list[str]:
    """The library backends that can time forward + backward on ``device`` (spconv's CPU build has no backward)."""
    from distilkit.sparse import backend

    if device.type != "cuda":
        return []
    return [name for name in ("spconv", "spconv-triton") if backend.problem(name, device.type) is None]


def on(name: str, fn: Any, form_name: str = "auto") -> Any:
    """``fn`` with the sparse convolutions on backend ``name`` (the torch path in form ``form_name``)."""
    from distilkit.sparse.backend import using
    from distilkit.sparse.form import using_form

    def run() -> Tensor:
        with using(name), using_form(form_name):
            return fn()
    return run


__all__ = ["compared", "library_backends", "on", "scan_occupancy", "sgemm_gflops", "sparse_cases", "sparse_size_cases",
           "tiled"]
