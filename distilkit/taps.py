"""Tap kinds: the named outputs an adapter's forward returns and objectives, task losses and metrics consume.

Each kind is registered with a check of its value (``TAP_KINDS``); the trainer checks every declared
tap of the student and the teacher on the first batch, so a wrong shape is one clear error up front.

| kind              | value                                                                     |
| ----------------- | ------------------------------------------------------------------------- |
| sparse_features   | :class:`SparseVoxels`: coords (N,4) int64 = batch,x,y,z; feats (N,C); grid  |
| voxel_logits      | (B, K, X, Y, Z) class scores on a voxel grid                              |
| feature_map       | dense features, either of the two below (what feature objectives read)    |
| image_features    | (B, C, H, W) features of a camera's image (a ``feature_map``)             |
| volume_features   | (B, C, X, Y, Z) features on a voxel grid (a ``feature_map``)              |
| bev_features      | (B, C, X, Y) features on a voxel grid's bird's-eye plane (a ``feature_map``) |
| occupancy_logits  | (B, 2, X, Y, Z) empty / occupied scores (VoxFormer's query proposals)     |
| depth_map         | (B, H, W) metres along a camera's axis, per pixel                         |
| point_logits      | (M, K) per-point class scores (points of the batch, concatenated)         |
| point_labels      | (M,) int64 labels of the points behind a ``point_logits`` tap             |
| points            | :class:`PointCloud`: (B, M, D) padded points and (B,) lengths (PyTorch3D's convention) |
| scalar            | a 0-d tensor                                                              |

A kind may refine a parent kind (``image_features`` is a ``feature_map``): a term that reads the parent
accepts taps of every refinement (:func:`kind_fits`). A recipe makes a ``bev_features`` tap of any voxel tap by
collapsing it over height (``taps: {bev: {of: completion, kind: bev_features, collapse: max}}``). Voxel taps live on a grid and image taps come from a
camera; adapters declare which (``Adapter.tap_grid``, ``Adapter.tap_camera``), so ``validate`` checks
alignments before training, and a :class:`SparseVoxels` value carries its grid's geometry. A plugin adds
a kind with :func:`register_tap_kind`.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any, Callable

from distilkit.structures import PointCloud, SparseVoxels  # noqa: F401  (the values of two kinds; re-exported)


@dataclass(frozen=True)
class TapKind:
    """A registered kind: ``check(value)`` returns None when the value fits, else what is wrong;
    ``parent`` is the kind it refines (a term reading the parent accepts it)."""

    name: str
    check: Callable[[Any], str | None]
    description: str
    parent: str | None = None


def _is_tensor(value: Any) -> bool:
    """Whether ``value`` is a tensor (without importing torch: no tensor exists before torch is imported)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, torch.Tensor)


def _shape(value: Any) -> str:
    return str(tuple(value.shape)) if _is_tensor(value) else type(value).__name__


def _tensor(dims: tuple[int, ...], what: str) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        if _is_tensor(value) and value.dim() in dims:
            return None
        return f"expected {what}, got {_shape(value)}"
    return check


def _labels(value: Any) -> str | None:
    if _is_tensor(value) and value.dim() == 1 and not value.dtype.is_floating_point:
        return None
    return f"expected (M,) integer labels, got {_shape(value)}" + (
        f" {value.dtype}" if _is_tensor(value) else "")


def _two_classes(value: Any) -> str | None:
    if _is_tensor(value) and value.dim() == 5 and value.shape[1] == 2:
        return None
    return f"expected (B, 2, X, Y, Z) empty/occupied scores, got {_shape(value)}"


def _instance(cls: type, what: str) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        return None if isinstance(value, cls) else f"expected {what}, got {_shape(value)}"
    return check


TAP_KINDS: dict[str, TapKind] = {}


def register_tap_kind(name: str, check: Callable[[Any], str | None], description: str,
                      parent: str | None = None) -> TapKind:
    """Register a tap kind ``name``: ``check`` says what is wrong with a value of it (None: nothing), the trainer
    calling it on every declared tap's first value; ``parent``: the kind it specialises (a term that reads the
    parent reads it too). A plug-in registers its own kinds at import."""
    if name in TAP_KINDS:
        raise ValueError(f"tap kind {name!r} is already registered")
    if parent is not None and parent not in TAP_KINDS:
        raise ValueError(f"tap kind {name!r} refines {parent!r}, which is not registered")
    TAP_KINDS[name] = kind = TapKind(name, check, description, parent)
    return kind


def kind_fits(kind: str, wanted: str) -> bool:
    """Whether a tap of ``kind`` serves a role that reads ``wanted`` (the kind itself or a refinement)."""
    while kind is not None:
        if kind == wanted:
            return True
        entry = TAP_KINDS.get(kind)
        kind = entry.parent if entry is not None else None  # type: ignore[assignment]
    return False


register_tap_kind("sparse_features", _instance(SparseVoxels, "SparseVoxels(coords, feats, spatial_shape)"),
                  "sparse voxel features on a grid")
register_tap_kind("voxel_logits", _tensor((5,), "(B, K, X, Y, Z) class scores"), "class scores per voxel")
register_tap_kind("feature_map", _tensor((4, 5), "(B, C, H, W) or (B, C, X, Y, Z) features"), "dense features")
register_tap_kind("image_features", _tensor((4,), "(B, C, H, W) image features"), "features of a camera image",
                  parent="feature_map")
register_tap_kind("volume_features", _tensor((5,), "(B, C, X, Y, Z) volume features"), "features on a voxel grid",
                  parent="feature_map")
register_tap_kind("bev_features", _tensor((4,), "(B, C, X, Y) bird's-eye-view features"),
                  "features on a voxel grid's (X, Y) plane: a BEV network's, or a volume's collapsed over height",
                  parent="feature_map")
register_tap_kind("occupancy_logits", _two_classes, "empty / occupied scores per voxel (query proposals)")
register_tap_kind("depth_map", _tensor((3,), "(B, H, W) depth in metres"), "a depth map of a camera image")
register_tap_kind("point_logits", _tensor((2,), "(M, K) per-point class scores"), "class scores per point")
register_tap_kind("point_labels", _labels, "labels of the points a model scored")
register_tap_kind("points", _instance(PointCloud, "PointCloud(points (B, M, D), lengths (B,))"),
                  "padded point clouds with lengths")
register_tap_kind("scalar", _tensor((0,), "a 0-d tensor"), "one number")


def to_float32(value: Any) -> Any:
    """A tap value with its floating tensors in float32 (reduced-precision model outputs, before the loss terms)."""
    if _is_tensor(value):
        import torch

        return value.float() if value.is_floating_point() and value.dtype != torch.float64 else value
    if isinstance(value, SparseVoxels):
        return value.with_feats(to_float32(value.feats))
    if isinstance(value, PointCloud):
        return PointCloud(to_float32(value.points), value.lengths)
    return value


DENSE_GRID_KINDS = frozenset({"voxel_logits", "volume_features", "occupancy_logits"})  # (B, C, X, Y, Z) on a grid


def publishable(kind: str | None) -> bool:
    """Whether a prediction of this kind can be published as labels (``publish``, a ``labels`` edge): class ids per
    voxel or point clouds."""
    return kind in ("voxel_logits", "points")


def check_tap(value: Any, kind: str, where: str) -> None:
    """Raise a clear error when a tap's value does not have the declared kind."""
    from distilkit.errors import TapError

    if kind not in TAP_KINDS:
        raise TapError(f"{where}: unknown tap kind {kind!r} (registered: {', '.join(TAP_KINDS)})")
    problem = TAP_KINDS[kind].check(value)
    if problem is not None:
        raise TapError(f"{where}: {problem} for a {kind} tap")


__all__ = ["DENSE_GRID_KINDS", "PointCloud", "SparseVoxels", "TAP_KINDS", "TapKind", "check_tap", "kind_fits", "publishable",
           "register_tap_kind", "to_float32"]
