"""VoxFormer's query proposals read from a folder (Li et al. CVPR 2023, stage 1): the class-agnostic occupancy its
release ships precomputed from stereo depth, one file per voxel frame.

Layout, from the release's stage-2 loader (``semantic_kitti_dataset_stage2.py``): ``<proposals>/NN/queries/
NNNNNN.<tag>`` — the authors' ``dataset/sequences_msnet3d_sweep10/NN/queries/NNNNNN.query_iou5203_pre7712_rec6153``
— each a bit-packed occupancy grid of half the voxel grid (128 x 128 x 16), C order, most significant bit first: the
packing of SemanticKITTI's ``.bin`` / ``.invalid`` voxel files. A relative ``proposals`` is under the dataset's
root. The field ``proposal`` is that grid (uint8, 1 = proposed), pooled by the dataset's scale (a coarse voxel is
proposed where any of its fine ones is); the ``voxformer`` adapter reads it where a stage-1 model's scores would be.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.errors import DataError

SHAPE = (128, 128, 16)  # half of SemanticKITTI's 256 x 256 x 32


def proposal_root(root: str | Path, proposals: str) -> Path:
    path = Path(proposals).expanduser()
    return path if path.is_absolute() else Path(root).expanduser() / path


def proposal_file(folder: Path, sequence: str, frame: int) -> Path | None:
    """The one proposal file of a frame (``NNNNNN.<tag>``), or None where there is none. Two files of one frame are
    an error (which one was meant cannot be told)."""
    found = sorted((folder / sequence / "queries").glob(f"{frame:06d}.*"))
    if len(found) > 1:
        raise DataError(f"{folder / sequence / 'queries'}: {len(found)} proposal files for frame {frame:06d} "
                        f"({', '.join(f.name for f in found[:3])}); keep one tag per folder")
    return found[0] if found else None


def read_proposal(path: Path, scale: int) -> np.ndarray:
    """One frame's proposed voxels (X, Y, Z) uint8 on the half-resolution grid coarsened by ``scale``."""
    bits = skio.read_voxel_bits(path, SHAPE)
    if scale > 1:
        x, y, z = SHAPE
        bits = bits.reshape(x // scale, scale, y // scale, scale, z // scale, scale).any(axis=(1, 3, 5))
    return bits.astype(np.uint8)


def write_proposal(path: Path, occupied: np.ndarray) -> None:
    """A proposal file in the release's packing (``occupied``: the (128, 128, 16) grid)."""
    if tuple(occupied.shape) != SHAPE:
        raise ValueError(f"a proposal grid is {SHAPE}, got {tuple(occupied.shape)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    skio.write_voxel_bits(path, occupied)


__all__ = ["SHAPE", "proposal_file", "proposal_root", "read_proposal", "write_proposal"]
