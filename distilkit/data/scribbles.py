"""ScribbleSC's voxel scribble labels (Scribble2Scene, Wang et al. IJCAI 2024) for a SemanticKITTI folder.

Layout, from the authors' release (``semantic_kitti_dataset_stage2.py::get_scribble_info``): a folder of its own,
``<scribbles>/sequences/NN/voxels/NNNNNN.label`` (the authors' ``./data/scribble_kitti/``), one uint16 raw
SemanticKITTI id per voxel of the 256 x 256 x 32 grid in the voxel files' order — the class of a scribbled voxel,
0 everywhere else — mapped through the completion learning map (0 stays 0, unlabelled ids become 255).

distilkit's ``scribble`` field tells empty from occupied-but-unscribbled with the dense geometry that ScribbleSC
provides beside its scribbles (the dense voxel labels' occupancy): a class id where a scribble labels the voxel,
254 (``SCRIBBLE_UNLABELLED``) where the voxel is occupied but unscribbled, 0 where it is empty, 255 where it is
invalid or its raw id has no class — the convention of the synthetic data's scribbles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.classes import IGNORE_INDEX, SCRIBBLE_UNLABELLED, remap, ssc_lut


def scribble_root(root: str | Path, scribbles: str) -> Path:
    """The ScribbleSC folder ``scribbles`` (a path under the dataset's ``root`` when relative)."""
    path = Path(scribbles).expanduser()
    return path if path.is_absolute() else Path(root).expanduser() / path


def scribble_file(folder: Path, sequence: str, frame: int) -> Path:
    return folder / "sequences" / sequence / "voxels" / f"{frame:06d}.label"


def read_scribbles(path: Path, dense: np.ndarray, invalid: np.ndarray, learning_map: dict[int, int]) -> np.ndarray:
    """The ``scribble`` field (X, Y, Z) uint8 of one frame from its ScribbleSC file, with the frame's dense voxel
    labels (train ids, 255 ignored) and invalid mask at full resolution (see the module docstring)."""
    raw = skio.read_voxel_labels(path, dense.shape)
    lab = remap(raw, ssc_lut(learning_map), str(path))
    out = np.where((dense != 0) & (dense != IGNORE_INDEX), SCRIBBLE_UNLABELLED, 0)
    out = np.where(lab != 0, lab, out)  # a scribbled voxel's class (255: a raw id without one)
    out = np.where(invalid, IGNORE_INDEX, out)
    return out.astype(np.uint8)


def pool_scribbles(scribble: np.ndarray, scale: int, num_classes: int) -> np.ndarray:
    """Coarsen a ``scribble`` grid by ``scale``: the majority scribbled class of the block, else 254 where a voxel of
    it is occupied but unscribbled, else 0 where one is empty, else 255 (all ignored)."""
    if scale == 1:
        return scribble
    x, y, z = scribble.shape
    blocks = scribble.reshape(x // scale, scale, y // scale, scale, z // scale, scale).transpose(0, 2, 4, 1, 3, 5)
    blocks = blocks.reshape(x // scale, y // scale, z // scale, -1)
    counts = np.stack([(blocks == c).sum(-1) for c in range(1, num_classes)], -1)
    out = np.where((blocks == IGNORE_INDEX).all(-1), IGNORE_INDEX, 0)
    out = np.where((blocks == SCRIBBLE_UNLABELLED).any(-1), SCRIBBLE_UNLABELLED, out)
    out = np.where(counts.max(-1) > 0, counts.argmax(-1) + 1, out)
    return out.astype(np.uint8)


def write_scribbles(path: Path, raw: np.ndarray) -> None:
    """One frame's ScribbleSC file: raw ids of the scribbled voxels, 0 elsewhere."""
    path.parent.mkdir(parents=True, exist_ok=True)
    skio.write_voxel_labels(path, raw)


__all__ = ["pool_scribbles", "read_scribbles", "scribble_file", "scribble_root", "write_scribbles"]
