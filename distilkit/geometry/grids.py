"""How two voxel grids of one volume map onto each other, in plain Python: ``validate`` checks taps' grids with it
before anything is built (no torch)."""

from __future__ import annotations

from distilkit.structures import VoxelGrid


def _grid_shape(grid: "VoxelGrid | tuple[int, ...]") -> tuple[int, ...]:
    return tuple(int(v) for v in (grid.shape if isinstance(grid, VoxelGrid) else grid))


def _geometry_problem(target: VoxelGrid, source: VoxelGrid) -> str | None:
    """Why two grids do not cover one volume with voxels that tile each other, or None when they do."""
    tol = 1e-6 * max(1.0, *(abs(v) for v in (*target.origin, *source.origin)))
    if any(abs(a - b) > tol for a, b in zip(target.origin, source.origin)):
        return f"origins {target.origin} and {source.origin} differ (the grids must share their min corner)"
    for t, s in zip(target.shape, source.shape):
        if abs(t * target.voxel_size - s * source.voxel_size) > 1e-6 * max(t * target.voxel_size, 1.0):
            return (f"extents {tuple(round(n * target.voxel_size, 6) for n in target.shape)} m and "
                    f"{tuple(round(n * source.voxel_size, 6) for n in source.shape)} m differ")
    return None


def grid_factors(target: "VoxelGrid | tuple[int, ...]",
                 source: "VoxelGrid | tuple[int, ...]") -> tuple[str, tuple[int, ...]] | str:
    """How ``source`` voxels map onto ``target`` voxels of the same volume.

    Grids given with their geometry (:class:`VoxelGrid`) must share origin and extent; bare shapes are
    taken to cover the same volume. Returns ``("same", 1s)``, ``("coarser", f)`` (source voxels are f_d
    target voxels wide), ``("finer", f)`` (f_d source voxels per target voxel), or a string saying why
    they cannot be aligned.
    """
    if isinstance(target, VoxelGrid) and isinstance(source, VoxelGrid):
        problem = _geometry_problem(target, source)
        if problem is not None:
            return f"grids {target.shape} and {source.shape} are not one volume: {problem}"
    target, source = _grid_shape(target), _grid_shape(source)
    if len(target) != len(source):
        return f"grids {target} and {source} have different dimensions"
    if target == source:
        return "same", tuple(1 for _ in target)
    if all(t % s == 0 for t, s in zip(target, source)):
        return "coarser", tuple(t // s for t, s in zip(target, source))
    if all(s % t == 0 for t, s in zip(target, source)):
        return "finer", tuple(s // t for t, s in zip(target, source))
    return (f"grids {target} and {source} differ by no integer factor per axis (voxels of one grid must tile "
            f"the other's)")


def plane_factors(target: "VoxelGrid", source: "VoxelGrid") -> tuple[str, tuple[int, ...]] | str:
    """:func:`grid_factors` of two grids' bird's-eye (X, Y) planes: their heights may differ (a BEV student's
    pillars beside a teacher's voxels), their planes must be one area tiled by integer factors."""
    if not isinstance(target, VoxelGrid) or not isinstance(source, VoxelGrid):
        return grid_factors(tuple(_grid_shape(target))[:2], tuple(_grid_shape(source))[:2])
    for axis, name in ((0, "x"), (1, "y")):
        lo = (target.origin[axis], source.origin[axis])
        hi = (lo[0] + target.shape[axis] * target.voxel_size, lo[1] + source.shape[axis] * source.voxel_size)
        if abs(lo[0] - lo[1]) > 1e-6 or abs(hi[0] - hi[1]) > 1e-6:
            return (f"they cover {name} from {lo[0]:g} to {hi[0]:g} m and from {lo[1]:g} to {hi[1]:g} m (one area is "
                    "needed)")
    return grid_factors(tuple(target.shape[:2]), tuple(source.shape[:2]))


__all__ = ["grid_factors", "plane_factors"]
