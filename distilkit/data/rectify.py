"""SCPNet's completion label rectification (Algorithm 1, SCPNet §3.4) as the paper intends it.

Completion labels fuse the labels of several scans, so moving objects leave long traces. For every dynamic class c:
the current scan's points whose own label is c are voxelised; for each of their *instances* the box of voxel
indices they occupy (bounds included) is kept; every voxel labelled c outside the union of those boxes is set to
``fill`` (255: ignored). Where the scan has no point of class c, every voxel of class c is removed.

The released code (seed_code.md §1.3) differs in three ways, each of which distilkit does not reproduce: it takes
the low 16 bits of the label (the semantic id) as the "instance", so one box spans every point of the class; it
slices ``[min:max)``, so an object one voxel thick gets an empty box and is wiped; and with no point of the class it
indexes with an int 0/1 array, which wipes x-slices 0 and 1 instead of the class's voxels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from distilkit.data.classes import CLASS_NAMES, IGNORE_INDEX, remap, seg_lut
from distilkit.structures import VoxelGrid

DEFAULT_DYNAMIC = ("car", "truck", "other-vehicle", "person", "bicyclist", "motorcyclist")  # SCPNet's [1,4,5,6,7,8]
POSS_DYNAMIC = ("people", "rider", "car")  # SemanticPOSS's moving classes
IGNORE_RAW = 1  # the raw id written for a removed voxel: "outlier", which the SSC table maps to 255 (ignored)


def dynamic_ids(names: Sequence[str], class_names: Sequence[str] = tuple(CLASS_NAMES)) -> list[int]:
    """Train ids of class names (default: SemanticKITTI's table); an unknown name is an error listing the known."""
    known = list(class_names)
    unknown = [n for n in names if n not in known[1:]]
    if unknown:
        raise ValueError(f"rectification classes {unknown} are not classes of the labels ({', '.join(known[1:])})")
    return [known.index(n) for n in names]


def rectify(voxel_label: np.ndarray, xyz: np.ndarray, point_raw: np.ndarray, grid: VoxelGrid,
            classes: Sequence[int] = tuple(dynamic_ids(DEFAULT_DYNAMIC)), fill: int = IGNORE_INDEX,
            learning_map: dict[int, int] | None = None) -> np.ndarray:
    """Rectified copy of ``voxel_label`` (X, Y, Z train ids on ``grid``) from the current scan's points ``xyz``
    (N, 3) in the grid's frame and their raw labels ``point_raw`` (N,) uint32: semantic id in the low 16 bits,
    instance id in the high 16 bits; ``learning_map``: the raw ids' train ids (default SemanticKITTI's)."""
    if voxel_label.shape != tuple(grid.shape):
        raise ValueError(f"rectify: labels of shape {voxel_label.shape} do not fit the grid {tuple(grid.shape)}")
    if len(xyz) != len(point_raw):
        raise ValueError(f"rectify: {len(xyz)} points but {len(point_raw)} labels")
    raw = np.asarray(point_raw).astype(np.uint32)
    semantic = remap(raw & 0xFFFF, seg_lut(learning_map), "point labels")
    instance = raw >> 16
    idx = np.floor((np.asarray(xyz, np.float64) - np.asarray(grid.origin)) / grid.voxel_size).astype(np.int64)
    inside = ((idx >= 0) & (idx < np.asarray(grid.shape))).all(axis=1)
    out = voxel_label.copy()
    for c in classes:
        of_class = voxel_label == c
        if not of_class.any():
            continue
        mine = (semantic == c) & inside
        keep = np.zeros(voxel_label.shape, bool)
        for inst in np.unique(instance[mine]):
            v = idx[mine & (instance == inst)]
            lo, hi = v.min(axis=0), v.max(axis=0) + 1  # the box includes its last voxel
            keep[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
        out[of_class & ~keep] = fill
    return out


def rectify_frame(d: Path, frame: int, labels: np.ndarray, classes: Sequence[int],
                  learning_map: dict[int, int] | None = None) -> np.ndarray:
    """:func:`rectify` of frame ``frame``'s full-resolution labels in sequence folder ``d``, with its own scan and
    panoptic labels (``velodyne/``, ``labels/``); a missing label file is an error that names it."""
    from distilkit.data import semantickitti as skio
    from distilkit.errors import DataError

    lab_file = d / "labels" / f"{frame:06d}.label"
    if not lab_file.is_file():
        raise DataError(f"{lab_file}: rectification needs the scan's point labels (panoptic), and there are none")
    xyz = skio.read_points(d / "velodyne" / f"{frame:06d}.bin")[:, :3]
    sem, inst = skio.read_point_labels(lab_file, len(xyz))
    raw = sem.astype(np.uint32) | (inst.astype(np.uint32) << 16)
    return rectify(labels, xyz, raw, VoxelGrid.semantickitti(1), classes, learning_map=learning_map)


def rectify_folder(root: str | Path, sequences: Sequence[str] | None = None,
                   classes: Sequence[str] | None = None, out: str = "voxels_rectified",
                   progress: Callable[[int, int], None] | None = None, table: Any = None) -> dict[str, tuple[int, int]]:
    """Rectify every ``voxels/NNNNNN.label`` of a SemanticKITTI-layout folder with its scan's panoptic labels, writing
    ``sequences/SS/<out>/NNNNNN.label`` beside the originals, which stay untouched: raw ids like theirs, a removed
    voxel as raw 1 (which both data sets' SSC tables ignore), every other voxel's raw id as it was. ``table``: the
    labels' :class:`~distilkit.data.info.ClassTable` (default SemanticKITTI's; ``classes`` default to its moving
    classes). Returns, per class name, (voxels before, voxels left)."""
    from distilkit.data import semantickitti as skio
    from distilkit.data.classes import ssc_lut
    from distilkit.data.info import ClassTable
    from distilkit.errors import DataError

    table = table or ClassTable.semantickitti()
    names = list(table.names)
    if classes is None:
        classes = POSS_DYNAMIC if names == list(ClassTable.semanticposs().names) else DEFAULT_DYNAMIC
    learning_map = dict(table.learning_map)

    base = Path(root).expanduser()
    seqs = sorted(sequences) if sequences else sorted(p.name for p in (base / "sequences").glob("*") if p.is_dir())
    jobs = []
    for seq in seqs:
        d = base / "sequences" / seq
        if not (d / "voxels").is_dir():
            raise DataError(f"{d}: no voxels/ folder (expected sequences/{seq}/voxels/NNNNNN.label)")
        jobs += [(d, f) for f in sorted((d / "voxels").glob("*.label"))]
    if not jobs:
        raise DataError(f"{base}: no sequences/*/voxels/*.label under the sequences {seqs}")
    ids = dynamic_ids(classes, names)
    counts = {names[c]: [0, 0] for c in ids}
    inverse = np.array([table.learning_map_inv.get(i, 0) for i in range(256)], np.uint16)
    inverse[IGNORE_INDEX] = IGNORE_RAW
    for n, (d, vox) in enumerate(jobs):
        raw_vox = skio.read_voxel_labels(vox)
        labels = remap(raw_vox, ssc_lut(learning_map), str(vox))
        fixed = rectify_frame(d, int(vox.stem), labels, ids, learning_map)
        for c in ids:
            counts[names[c]][0] += int((labels == c).sum())
            counts[names[c]][1] += int((fixed == c).sum())
        out_raw = np.where(fixed == labels, raw_vox, inverse[fixed]).astype(np.uint16)
        (d / out).mkdir(exist_ok=True)
        skio.write_voxel_labels(d / out / vox.name, out_raw)
        if progress:
            progress(n + 1, len(jobs))
    return {k: (v[0], v[1]) for k, v in counts.items()}


__all__ = ["DEFAULT_DYNAMIC", "POSS_DYNAMIC", "dynamic_ids", "rectify", "rectify_folder", "rectify_frame"]
