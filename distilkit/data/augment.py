"""A finite group of rigid transforms of a scene about the vertical axis — flips of the grid's x and y axes and
90° rotations about z — applied to every field of a sample alike, so that each target stays aligned with the input.

JS3C-Net trains SSC with "random flip along the x-axis and z-axis, and randomly rotate along y-axis by 90 degrees"
and votes over augmented copies at inference (Yan et al., AAAI 2021, "Joint Learning Protocol"; its volume's y axis
is the vertical one, so in SemanticKITTI's frame — x forward, y left, z up — these are flips of x and y and a
quarter turn about z); SCPNet's release has its augmentation commented out. Flips of two axes and quarter turns
generate the 8 transforms of the square's symmetry group (the dihedral group D4: flipping x then y is the rotation
by 180°). Read as "rotate by 90° or not", the paper's 2 × 2 × 2 combinations are those 8 transforms once each; read
as "by a multiple of 90°", its 2 × 2 × 4 combinations are each transform twice — either way every transform is
drawn with probability 1/8, which is what distilkit does: it enumerates the distinct transforms (:func:`elements`)
and draws among them.

A transform acts on the grid's horizontal plane about the grid's centre (a dataset without a grid: about the sensor,
x = y = 0), z unchanged. Per field of a sample (:func:`transform_sample`):

* point clouds (``points``, ``scan``, ``scene``, ``scene_eval``: (N, ≥3) metres): x, y transformed;
* voxel grids (``voxel_label``, ``invalid``, ``scribble``, ``occluded``, ``proposal`` — the last at half the
  resolution): the array permuted so that voxel (i, j) goes where its centre goes (a rotation needs a square grid);
* ``lidar_to_camera`` ((T, 4, 4)): composed with the inverse transform, so the camera still sees the scene it saw
  (the image, its depth and intrinsics do not change);
* per point or per sample (``point_frame``, ``point_label``, ``image``, ``intrinsics``, ``depth``, ids): unchanged.

A field of none of these kinds is refused with its name (a transform could not keep it aligned).

**Continuous** transforms (``rotate``, ``tilt``, ``scale`` of :class:`~distilkit.recipe.augment.AugmentSpec`) are
LiDiff's training transforms (``utils/pcd_transforms.py``, applied in ``TemporalKITTISet.transforms`` to the scan and
the scene together; ScoreLiDAR's loader is the same): a uniform turn about z, then a tilt by three angles each
N(0, 0.06²) clipped to ±0.18 rad, then a scale in [0.95, 1.05], then a flip of y with probability 1/2 — the same
distributions, drawn from distilkit's per-sample stream (LiDiff multiplies row vectors, ``p @ R``: the transpose
of each rotation, which has the same distribution for symmetric angles, and it tilts as ``Rz·Ry·Rx`` on rows, i.e.
``Rx·Ry·Rz`` on columns, as here). They act about the sensor (x = y = z = 0), as LiDiff's do, on point clouds and
camera poses; a voxel grid cannot follow them and is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

POINT_FIELDS = frozenset({"points", "scan", "scene", "scene_eval"})
GRID_FIELDS = frozenset({"voxel_label", "invalid", "scribble", "occluded", "proposal"})
CAMERA_POSE_FIELDS = frozenset({"lidar_to_camera"})
UNCHANGED_FIELDS = frozenset({"point_frame", "point_label", "image", "intrinsics", "depth", "scene_id", "sample_id"})

_ROTATE = np.array([[0, -1], [1, 0]])  # +90° about z: (x, y) -> (-y, x), as np.rot90(axes=(0, 1)) turns an array


@dataclass(frozen=True)
class Element:
    """One transform: flip x, then flip y, then ``turns`` rotations by +90° about z."""

    flip_x: bool = False
    flip_y: bool = False
    turns: int = 0

    @property
    def matrix(self) -> np.ndarray:
        """The 2 × 2 integer matrix acting on (x, y) about the centre."""
        flips = np.diag([-1 if self.flip_x else 1, -1 if self.flip_y else 1])
        return np.linalg.matrix_power(_ROTATE, self.turns) @ flips

    @property
    def name(self) -> str:
        parts = [p for p, on in (("flip x", self.flip_x), ("flip y", self.flip_y)) if on]
        parts += [f"rotate {90 * self.turns}°"] if self.turns else []
        return ", ".join(parts) or "identity"


def elements(flip: tuple[str, ...] | list[str] = (), rotate90: bool = False) -> list[Element]:
    """The distinct transforms that flips of the axes in ``flip`` and (``rotate90``) quarter turns about z generate,
    the identity first (each combination of flips and turns kept once per distinct matrix)."""
    out: list[Element] = []
    seen: list[np.ndarray] = []
    for turns in (range(4) if rotate90 else (0,)):
        for fy in ((False, True) if "y" in flip else (False,)):
            for fx in ((False, True) if "x" in flip else (False,)):
                e = Element(fx, fy, turns)
                if not any(np.array_equal(e.matrix, m) for m in seen):
                    seen.append(e.matrix)
                    out.append(e)
    return out


def inverse(e: Element) -> Element:
    """The transform that undoes ``e`` (test-time voting maps each copy's prediction back with it)."""
    for candidate in elements(["x", "y"], rotate90=True):
        if np.array_equal(candidate.matrix @ e.matrix, np.eye(2, dtype=int)):
            return candidate
    raise AssertionError(f"{e} has no inverse among the flips and quarter turns")  # the group is closed


def group_of(spec: Any) -> list[Element]:
    """The transforms of an augmentation spec (:class:`~distilkit.recipe.schema.AugmentSpec`)."""
    return elements(spec.flip, spec.rotate90 is not None)


def _grid_centre(grid: Any) -> np.ndarray:
    if grid is None:
        return np.zeros(2)
    return np.array([grid.origin[0] + grid.shape[0] * grid.voxel_size / 2,
                     grid.origin[1] + grid.shape[1] * grid.voxel_size / 2])


def transform_points(points: np.ndarray, e: Element, grid: Any) -> np.ndarray:
    """(N, ≥3) points with x, y transformed about the grid's centre; the other columns as they were."""
    if e == Element():
        return points
    c = _grid_centre(grid)
    out = np.array(points, copy=True)
    xy = out[:, :2].astype(np.float64) - c
    out[:, :2] = (xy @ e.matrix.T + c).astype(out.dtype)
    return out


def transform_grid(array: np.ndarray, e: Element) -> np.ndarray:
    """A (X, Y, ...) array permuted so that voxel (i, j) goes where its centre goes."""
    if e.turns % 2 and array.shape[0] != array.shape[1]:
        raise ValueError(f"a 90° rotation needs a square grid in x and y, got {array.shape[:2]}")
    out = array
    if e.flip_x:
        out = out[::-1]
    if e.flip_y:
        out = out[:, ::-1]
    if e.turns:
        out = np.rot90(out, e.turns, axes=(0, 1))
    return np.ascontiguousarray(out)


def affine(e: Element, grid: Any) -> np.ndarray:
    """The (4, 4) map of a point of the original scene to the transformed scene."""
    c = _grid_centre(grid)
    out = np.eye(4)
    out[:2, :2] = e.matrix
    out[:2, 3] = c - e.matrix @ c
    return out


def _move_fields(sample: dict[str, Any], pose: Callable[[], np.ndarray], points: Callable[[np.ndarray], np.ndarray],
                 grid: Callable[[str, np.ndarray], np.ndarray], what: str) -> dict[str, Any]:
    """Every field of a sample moved alike: point clouds by ``points``, voxel grids by ``grid``, camera poses by the
    inverse of the (4, 4) ``pose()``; fields known to be unchanged kept; any other array refused, as it could not be
    kept aligned (``what``: the transforms, for the message)."""
    out: dict[str, Any] = {}
    for key, value in sample.items():
        if key in POINT_FIELDS:
            out[key] = points(value)
        elif key in GRID_FIELDS:
            out[key] = grid(key, value)
        elif key in CAMERA_POSE_FIELDS:
            out[key] = (np.asarray(value, dtype=np.float64) @ np.linalg.inv(pose())).astype(np.asarray(value).dtype)
        elif key in UNCHANGED_FIELDS or not isinstance(value, np.ndarray):
            out[key] = value
        else:
            raise ValueError(f"train.augment: the sample's field {key!r} is not a point cloud, a voxel grid, a camera "
                             f"pose or a field known to be unchanged by {what}, so it could not be kept aligned "
                             "(known: " + ", ".join(sorted(POINT_FIELDS | GRID_FIELDS | CAMERA_POSE_FIELDS
                                                          | UNCHANGED_FIELDS)) + ")")
    return out


def transform_sample(sample: dict[str, Any], e: Element, grid: Any) -> dict[str, Any]:
    """Every field of a sample transformed by ``e`` (see the module docstring); the identity returns it as it is."""
    if e == Element():
        return sample
    return _move_fields(sample, lambda: affine(e, grid), lambda v: transform_points(v, e, grid),
                        lambda key, v: transform_grid(v, e), "a flip or rotation")


def _turn(axis: int, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` radians about axis 0, 1 or 2 (column vectors)."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = [a for a in range(3) if a != axis]
    out = np.eye(3)
    out[i, i], out[i, j], out[j, i], out[j, j] = c, -s, s, c
    return out


def continuous_affine(spec: Any, draw: int) -> np.ndarray:
    """The (4, 4) transform about the sensor that ``draw`` (a seed) picks from a continuous spec, LiDiff's order:
    turn, tilt, scale, flips (then quarter turns, where asked)."""
    rng = np.random.default_rng(draw)
    m = np.eye(3)
    if spec.rotate is not None:
        m = _turn(2, rng.uniform(0.0, 2 * np.pi)) @ m
    if spec.tilt is not None:
        a, b, c = np.clip(spec.tilt.sigma * rng.standard_normal(3), -spec.tilt.clip, spec.tilt.clip)
        m = _turn(0, a) @ _turn(1, b) @ _turn(2, c) @ m
    if spec.scale is not None:
        m = rng.uniform(spec.scale[0], spec.scale[1]) * m
    for axis in ("x", "y"):
        if axis in spec.flip and rng.random() > 0.5:  # LiDiff's random_flip_point_cloud: y, probability 1/2
            m = np.diag([-1.0 if axis == "x" else 1.0, -1.0 if axis == "y" else 1.0, 1.0]) @ m
    if spec.rotate90 is not None:
        m = _turn(2, np.pi / 2 * int(rng.integers(4))) @ m
    out = np.eye(4)
    out[:3, :3] = m
    return out


def transform_continuous(sample: dict[str, Any], a: np.ndarray) -> dict[str, Any]:
    """Every field of a sample moved by the (4, 4) affine ``a``: point clouds and camera poses; a voxel grid is
    refused (it cannot follow a continuous transform)."""
    def points(value: np.ndarray) -> np.ndarray:
        moved = np.array(value, copy=True)
        moved[:, :3] = (value[:, :3].astype(np.float64) @ a[:3, :3].T + a[:3, 3]).astype(moved.dtype)
        return moved

    def grid(key: str, value: np.ndarray) -> np.ndarray:
        raise ValueError(f"train.augment: rotate, tilt and scale are continuous: the sample's voxel grid {key!r} "
                         "cannot follow them (only flips and quarter turns move voxels onto voxels)")
    return _move_fields(sample, lambda: a, points, grid, "a rotation or scale")


class Augmentation:
    """What a stage's ``train.augment`` draws: a finite group's element (an index), or — with a continuous part — a
    transform picked by a 32-bit seed. ``draws``: how many values a draw takes (the batch plan draws one per
    sample and step)."""

    def __init__(self, spec: Any, grid: Any) -> None:
        self.spec, self.grid = spec, grid
        self.group = [] if spec.continuous else group_of(spec)

    @property
    def draws(self) -> int:
        return 2 ** 32 if self.spec.continuous else len(self.group)

    def apply(self, sample: dict[str, Any], draw: int) -> dict[str, Any]:
        if self.spec.continuous:
            return transform_continuous(sample, continuous_affine(self.spec, draw))
        return transform_sample(sample, self.group[draw], self.grid)


class Augmented:
    """A training split whose item ``(index, draw)`` is sample ``index`` under the augmentation's ``draw`` (an
    integer index: the sample as it is — what a term's ``prepare`` reads for the split's statistics)."""

    def __init__(self, dataset: Any, augmentation: Augmentation) -> None:
        self.dataset, self.augmentation = dataset, augmentation

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, key: Any) -> Any:
        if isinstance(key, tuple):  # the draw rides along: a teacher store reads the sample's rows under it
            index, draw = key
            return {**self.augmentation.apply(self.dataset[index], draw), "augment_draw": int(draw)}
        return self.dataset[key]

    def __getattr__(self, name: str) -> Any:  # the split's other attributes (its notes, its sample ids)
        if name in ("dataset", "augmentation"):
            raise AttributeError(name)
        return getattr(self.dataset, name)


__all__ = ["Augmentation", "Augmented", "Element", "affine", "continuous_affine", "elements", "group_of", "inverse",
           "transform_continuous", "transform_grid", "transform_points", "transform_sample"]
