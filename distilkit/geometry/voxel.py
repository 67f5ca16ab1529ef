"""Voxel grids in SemanticKITTI conventions, voxel hashing and sparse feature alignment."""

from __future__ import annotations

import torch
from torch import Tensor

from distilkit.geometry.grids import grid_factors  # noqa: F401  (re-exported)
from distilkit.structures import SparseVoxels, VoxelGrid  # noqa: F401  (VoxelGrid re-exported)


def voxel_hash(coords: Tensor, spatial_shape: tuple[int, int, int]) -> Tensor:
    """Unique int64 key of (batch, x, y, z) rows: ((b*X + x)*Y + y)*Z + z."""
    x, y, z = spatial_shape
    c = coords.long()
    return ((c[:, 0] * x + c[:, 1]) * y + c[:, 2]) * z + c[:, 3]


def align_sparse(target_coords: Tensor, source: SparseVoxels) -> tuple[Tensor, Tensor]:
    """Gather ``source`` features at ``target_coords`` (N,4); zero rows where the source has no voxel.

    This is the DSKD alignment choice (SCPNet §3.3; as in the jdgalviss re-implementation,
    seed_code.md §1.1): the student's voxel set is the reference, teacher rows are looked up at
    the student's coordinates by sorted hash + searchsorted, O((N + M) log M).

    Returns:
        feats: (N, C) aligned source features; found: (N,) bool, True where the source had the voxel.
    """
    if source.coords.shape[0] == 0:
        return source.feats.new_zeros((target_coords.shape[0], source.feats.shape[1])), torch.zeros(
            target_coords.shape[0], dtype=torch.bool, device=target_coords.device)
    src_key = voxel_hash(source.coords, source.spatial_shape)
    order = torch.argsort(src_key)
    sorted_key = src_key[order]
    tgt_key = voxel_hash(target_coords, source.spatial_shape)
    pos = torch.searchsorted(sorted_key, tgt_key).clamp_max(sorted_key.numel() - 1)
    found = sorted_key[pos] == tgt_key
    rows = order[pos]
    feats = source.feats[rows] * found.unsqueeze(1).to(source.feats.dtype)
    return feats, found


def align_across_grids(target_coords: Tensor, target_grid: "VoxelGrid | tuple[int, int, int]",
                       source: SparseVoxels) -> tuple[Tensor, Tensor]:
    """Source features at each target voxel, for grids of the same volume differing by integer factors.

    * same grid: :func:`align_sparse` (exact lookup);
    * source coarser: gather at scaled coordinates (each target voxel reads its parent voxel);
    * source finer: pool first (the mean over the parent's active source voxels), then look up.

    Returns (N, C) features and the (N,) bool mask of target voxels the source covers; raises
    :class:`~distilkit.errors.GridMismatchError` naming both grids when they cannot be aligned.
    """
    from distilkit.errors import GridMismatchError

    how = grid_factors(target_grid, source.grid if source.grid is not None and isinstance(target_grid, VoxelGrid)
                       else source.spatial_shape)
    if isinstance(how, str):
        raise GridMismatchError(f"cannot align sparse voxels: {how}")
    mode, f = how
    if mode == "same":
        return align_sparse(target_coords, source)
    factor = torch.tensor((1, *f), device=target_coords.device, dtype=torch.long)
    if mode == "coarser":
        return align_sparse(target_coords // factor, source)
    parent = source.coords // factor
    shape = tuple(int(s) // int(k) for s, k in zip(source.spatial_shape, f))
    keys, inv = torch.unique(voxel_hash(parent, shape), return_inverse=True)  # type: ignore[arg-type]
    counts = torch.bincount(inv, minlength=keys.numel()).clamp_min(1).to(source.feats.dtype)
    pooled = source.feats.new_zeros((keys.numel(), source.feats.shape[1])).index_add_(0, inv, source.feats)
    coords = torch.zeros((keys.numel(), 4), dtype=torch.long, device=parent.device)
    coords[inv] = parent
    return align_sparse(target_coords, SparseVoxels(coords, pooled / counts[:, None], shape))  # type: ignore[arg-type]


def dense_to_sparse(dense: Tensor, grid: VoxelGrid | None = None) -> SparseVoxels:
    """Extract non-zero voxels of a dense (B, C, X, Y, Z) volume (``sum |feat| > 0``), SCPNet §3.2;
    ``grid`` is the volume's geometry, where known."""
    if dense.dim() != 5:
        raise ValueError(f"dense_to_sparse expects (B, C, X, Y, Z), got {tuple(dense.shape)}")
    active = dense.detach().abs().sum(dim=1) > 0  # (B, X, Y, Z)
    coords = active.nonzero()  # sorted lexicographically: batch, x, y, z
    feats = dense.permute(0, 2, 3, 4, 1)[active]
    return SparseVoxels(coords, feats, tuple(dense.shape[2:]), grid)  # type: ignore[arg-type]


def pool_occupancy(target: Tensor, factor: int, ignore_index: int = 255) -> Tensor:
    """(B, X/f, Y/f, Z/f) occupancy of a label grid (B, X, Y, Z) coarsened by ``factor``: 1 where a block holds an
    occupied voxel (label neither 0 nor ``ignore_index``), else 0 where it holds an empty one, else ``ignore_index``
    (VoxFormer's binarised half-resolution geometry)."""
    if factor == 1:
        occ = (target != 0) & (target != ignore_index)
        return torch.where(target == ignore_index, target.new_tensor(ignore_index), occ.long())
    b, x, y, z = target.shape
    if x % factor or y % factor or z % factor:
        raise ValueError(f"pool_occupancy: grid {(x, y, z)} is not divisible by {factor}")
    blocks = target.reshape(b, x // factor, factor, y // factor, factor, z // factor, factor)
    occupied = ((blocks != 0) & (blocks != ignore_index)).amax(dim=(2, 4, 6))
    empty = (blocks == 0).amax(dim=(2, 4, 6))
    out = torch.full(occupied.shape, ignore_index, dtype=torch.long, device=target.device)
    return out.masked_fill(empty, 0).masked_fill(occupied, 1)

