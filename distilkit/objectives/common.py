"""Helpers shared by objectives: voxel masks from a batch, dense-map resampling."""

from __future__ import annotations

import contextlib

import torch
import torch.nn.functional as F
from torch import Tensor

from distilkit.cards.objectives.common import MaskName
from distilkit.data.classes import IGNORE_INDEX
from distilkit.errors import GridMismatchError, TapError
from distilkit.geometry.voxel import align_across_grids
from distilkit.losses.ce import deterministic_form_needed
from distilkit.losses.proposal import linear_resize_matrix
from distilkit.structures import SparseVoxels

__all__ = ["MaskName", "adaptive_pool_matrix", "aligned_pairs", "conv1x1", "map_pairs", "match_spatial", "occupied_at",
           "release_labels", "voxel_mask"]


def voxel_mask(target: Tensor, which: str, ignore_index: int = IGNORE_INDEX) -> Tensor | None:
    """(B, X, Y, Z) bool from a (B, X, Y, Z) label grid (a term's ``target`` batch role, ``voxel_target`` by
    default): ``all`` -> None, ``valid`` = observed and labelled (target != ``ignore_index``, the class table's),
    ``occupied`` = valid and non-empty."""
    if which == "all":
        return None
    if which == "valid":
        return target != ignore_index
    if which == "occupied":
        return (target != ignore_index) & (target != 0)
    raise ValueError(f"unknown voxel mask {which!r} (all, valid or occupied)")


def aligned_pairs(student: SparseVoxels, teacher: SparseVoxels) -> tuple[Tensor, Tensor, Tensor]:
    """Student rows, the (detached) teacher rows at the student's voxels (zero where the teacher has
    none), and the mask of voxels the teacher has.

    The student's voxels are the reference set. Across grids of the same volume that differ by
    integer factors the alignment is geometric (when both taps carry their grid, origin and extent are
    checked too): a coarser teacher is gathered at the student's
    scaled coordinates (its parent voxel); a finer teacher is first pooled into the student's
    voxels (mean over the active child voxels). See :func:`distilkit.geometry.voxel.align_across_grids`.
    """
    target = student.grid if student.grid is not None and teacher.grid is not None else student.spatial_shape
    try:
        t, found = align_across_grids(student.coords, target, teacher.detach())
    except GridMismatchError as exc:
        raise GridMismatchError(f"student grid {tuple(student.spatial_shape)} and teacher grid "
                                f"{tuple(teacher.spatial_shape)} cannot be aligned: {exc}") from None
    return student.feats, t, found


def adaptive_pool_matrix(n_in: int, n_out: int, dtype: torch.dtype = torch.float64,
                         device: torch.device | str | None = None) -> Tensor:
    """(n_out, n_in): adaptive average pooling along one axis as PyTorch does it (output i averages the inputs
    floor(i n_in / n_out) .. ceil((i + 1) n_in / n_out) - 1), as a matrix."""
    i = torch.arange(n_out, dtype=torch.float64)
    start = torch.floor(i * n_in / n_out).long()
    end = torch.ceil((i + 1) * n_in / n_out).long()
    j = torch.arange(n_in)
    inside = (j[None, :] >= start[:, None]) & (j[None, :] < end[:, None])
    m = inside.double() / (end - start).double()[:, None]
    return m.to(dtype=dtype, device=device)


def _separable(x: Tensor, matrices: list[Tensor]) -> Tensor:
    """``x`` (B, C, *S) with each spatial axis multiplied by its (S'_d, S_d) matrix."""
    for d, m in enumerate(matrices):
        axis = 2 + d
        x = (x.movedim(axis, -1) @ m.t()).movedim(-1, axis)
    return x


def match_spatial(x: Tensor, shape: tuple[int, ...], deterministic: bool | None = None) -> Tensor:
    """Resample a (B, C, *S) map to spatial ``shape`` (adaptive average pooling down, trilinear/bilinear up).

    ``deterministic`` (default: off the CPU under deterministic algorithms,
    :func:`~distilkit.losses.ce.deterministic_form_needed`): as one product per axis with the pooling or linear
    interpolation matrix (both are separable), instead of PyTorch's kernels, whose CUDA backward PyTorch flags
    (``adaptive_avg_pool3d_backward_cuda``, ``upsample_trilinear3d_backward_out_cuda`` "does not have a deterministic
    implementation"). The same up to the rounding of the weights; the products in float32 at least."""
    if tuple(x.shape[2:]) == tuple(shape):
        return x
    down = all(a >= b for a, b in zip(x.shape[2:], shape))
    if deterministic if deterministic is not None else deterministic_form_needed(x):
        work = torch.promote_types(x.dtype, torch.float32)
        make = adaptive_pool_matrix if down else linear_resize_matrix
        matrices = [make(int(a), int(b), work, x.device) for a, b in zip(x.shape[2:], shape)]
        with torch.autocast(x.device.type, enabled=False) if x.is_cuda else contextlib.nullcontext():
            return _separable(x.to(work), matrices).to(x.dtype)
    if down:
        pool = F.adaptive_avg_pool3d if x.dim() == 5 else F.adaptive_avg_pool2d
        return pool(x, shape)
    return F.interpolate(x, size=shape, mode="trilinear" if x.dim() == 5 else "bilinear", align_corners=False)


def conv1x1(cin: int, cout: int, dims: int) -> torch.nn.Module:
    return (torch.nn.Conv3d if dims == 3 else torch.nn.Conv2d)(cin, cout, 1)


def release_labels(target: Tensor, ignore_index: int) -> Tensor:
    """The data's labels with its ignore label as 255 (the releases' convention)."""
    return torch.where(target == ignore_index, torch.full_like(target, 255), target)


def occupied_at(labels: Tensor, shape: tuple[int, ...]) -> Tensor:
    """(B, *shape) bool: where a block of the label grid holds a labelled non-empty voxel (label not 0 nor 255) —
    the release's ``target != 0`` at the feature's resolution (its 2-D planes: the mean over the collapsed axis
    != 0). A 2-D map is taken as the (X, Y) plane; the grid must be an integer multiple of the map."""
    occ = ((labels != 0) & (labels != 255)).float()
    if len(shape) == 2 and occ.dim() == 4:
        occ = occ.amax(dim=3)
    if len(shape) != occ.dim() - 1:
        raise GridMismatchError(f"labels {tuple(labels.shape[1:])} and a feature map {shape}: no common axes")
    factors = [a // b if b and a % b == 0 else 0 for a, b in zip(occ.shape[1:], shape)]
    if not all(factors):
        raise GridMismatchError(f"labels {tuple(labels.shape[1:])} are not an integer multiple of the feature map "
                                f"{shape}")
    pool = F.max_pool3d if len(shape) == 3 else F.max_pool2d
    return pool(occ[:, None], kernel_size=factors)[:, 0] > 0


def map_pairs(taps: dict[str, object], extra: list[tuple[str, str]], term: str) -> list[tuple[str, str]]:
    """The (student, teacher) roles of a term's map pairs: ``student``/``teacher``, then each of ``extra``
    (``student_2``/``teacher_2``, ...) the recipe names both taps of; one named alone is an error."""
    pairs = [("student", "teacher")]
    for s_role, t_role in extra:
        if (s_role in taps) != (t_role in taps):
            raise TapError(f"{term}: {s_role if s_role in taps else t_role} is given without "
                           f"{t_role if s_role in taps else s_role} (name both taps of a pair)")
        if s_role in taps:
            pairs.append((s_role, t_role))
    return pairs
