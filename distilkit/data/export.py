"""``distilkit data export-kitti``: synthetic streets written as a SemanticKITTI folder, so that the real-data path
(reading, multi-scan fusion, rectification, training, prediction, evaluation) runs end to end without the real data.

Each sequence is one drive along a synthetic street (``frames`` scans, the ego moving ``ego_speed`` metres a frame):

* ``velodyne/NNNNNN.bin``: float32 x, y, z, remission in the sensor frame;
* ``labels/NNNNNN.label``: uint32, raw semantic id in the low 16 bits, instance id in the high 16 (moving objects
  carry the moving-* ids, as SemanticKITTI's);
* ``voxels/NNNNNN.label|.invalid|.bin|.occluded`` for every ``stride``-th frame: the scans t .. t + ``gt_frames`` (as
  many as the sequence has) fused in frame t and voxelised on the 256 x 256 x 32 grid (majority raw id, uint16), the
  voxels no ray of them traversed (packed bits, ``np.packbits`` order), the current scan's occupancy (packed bits) and
  the voxels neither it occupies nor its rays cross (hidden from the current viewpoint) — moving objects leave
  traces, as in the real data;
* ``image_2/NNNNNN.png`` for every frame when the synthetic parameters have a ``camera`` (rendered as the
  ``synthetic-lidar`` camera renders, at its image size);
* ScribbleSC's scribbles in their own folder, ``scribblesc/sequences/NN/voxels/NNNNNN.label`` beside ``sequences/``
  (:mod:`distilkit.data.scribbles`; ``scribbles: scribblesc`` reads them): for every voxel frame, the majority raw id
  of the fused points the synthetic annotator's scribbles cover (lines fixed in the world, as the ``synthetic-lidar``
  scribbles), 0 elsewhere;
* ``poses.txt`` (camera-0 poses, KITTI's convention) and ``calib.txt`` whose ``Tr`` is the LiDAR-to-camera transform
  (KITTI's axes, cam2's offset; ``P2``'s intrinsics are the written images'), so that ``inv(Tr) · P · Tr`` gives the
  LiDAR poses back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.camera import CAMERA_IN_LIDAR, KITTI_CENTRE, KITTI_FOCAL, LIDAR_TO_CAMERA_AXES, intrinsics
from distilkit.data.params import SyntheticParams
from distilkit.data.raycast import ray_directions
from distilkit.errors import DistilkitError
from distilkit.data.scribbles import write_scribbles
from distilkit.data.street_layout import EGO_LANE_Y, SENSOR_HEIGHT, make_scene
from distilkit.data.synthetic import cast_scan, scribble_mask, traversed, voxelize_majority
from distilkit.structures import VoxelGrid


def lidar_to_camera() -> np.ndarray:
    """KITTI's ``Tr``: LiDAR (x forward, y left, z up) to camera (x right, y down, z forward), cam2's offset."""
    tr = np.eye(4)
    tr[:3, :3] = LIDAR_TO_CAMERA_AXES
    tr[:3, 3] = -LIDAR_TO_CAMERA_AXES @ CAMERA_IN_LIDAR
    return tr


def _row(m: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in m[:3, :4].reshape(-1))


def write_calib(path: Path, tr: np.ndarray, k: np.ndarray | None = None) -> None:
    """``calib.txt``: P0..P3 = K [I | 0] (KITTI's cam2 intrinsics, or ``k``: those of the images written), ``Tr``."""
    p = np.zeros((3, 4))
    if k is None:
        p[0, 0] = p[1, 1] = KITTI_FOCAL
        p[:2, 2], p[2, 2] = KITTI_CENTRE, 1.0
    else:
        p[:, :3] = k
    path.write_text("".join(f"P{i}: {_row(p)}\n" for i in range(4)) + f"Tr: {_row(tr)}\n")


def export_sequence(seq_dir: Path, seed: int, p: SyntheticParams, frames: int, stride: int,
                    progress: Callable[[], None] | None = None, scribble_dir: Path | None = None) -> int:
    """Write one drive of ``frames`` scans into ``seq_dir`` (and its scribbles into ``scribble_dir``, a ScribbleSC
    sequence folder); returns the number of voxel frames written."""
    for sub in ("velodyne", "labels", "voxels"):
        (seq_dir / sub).mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    x0 = rng.uniform(0, 20)
    scene = make_scene(rng, x0 - 20, x0 + p.ego_speed * frames + 80, p.ego_speed, x0, frames)
    dirs = ray_directions(p.beams, p.azimuth_steps, p.fov_up, p.fov_down)
    grid = VoxelGrid.semantickitti(1)
    origins = [np.array([x0 + p.ego_speed * j, EGO_LANE_Y, SENSOR_HEIGHT], np.float32) for j in range(frames)]
    scans = [cast_scan(scene, origins[j], j, dirs, rng, p.max_range, p.range_noise) for j in range(frames)]
    tr = lidar_to_camera()
    if p.camera is not None:
        from distilkit.data.kitti_camera import write_image
        from distilkit.data.render import render

        (seq_dir / "image_2").mkdir(exist_ok=True)
        for j in range(frames):  # the camera of frame j, the traffic where it was then; the images' own stream
            image, _ = render(scene, origins[0], j, p.camera, p.ego_speed, np.random.default_rng([seed, 0xCA, j]))
            write_image(seq_dir / "image_2" / f"{j:06d}.png", image)
    poses = []
    for j, s in enumerate(scans):
        local = s.xyz - origins[j][None, :]  # heading 0: the sensor frame is the world shifted
        np.concatenate([local, s.intensity[:, None]], 1).astype("<f4").tofile(seq_dir / "velodyne" / f"{j:06d}.bin")
        skio.write_point_labels(seq_dir / "labels" / f"{j:06d}.label", s.label, s.inst)
        pose = np.eye(4)
        pose[:3, 3] = origins[j] - origins[0]
        poses.append(tr @ pose @ np.linalg.inv(tr))  # camera-0 poses, as KITTI stores them
    written = 0
    for t in range(0, frames, stride):
        last = min(t + p.gt_frames, frames - 1)
        fused = [scans[j].xyz - origins[t][None, :] for j in range(t, last + 1)]
        raw = np.concatenate([scans[j].label for j in range(t, last + 1)])
        voxel_raw = voxelize_majority(np.concatenate(fused), raw, grid)
        seen = traversed([origins[j] - origins[t] for j in range(t, last + 1)], fused, grid)
        skio.write_voxel_labels(seq_dir / "voxels" / f"{t:06d}.label", voxel_raw.astype(np.uint16))
        skio.write_voxel_bits(seq_dir / "voxels" / f"{t:06d}.invalid", ~seen & (voxel_raw == 0))
        occupied = voxelize_majority(fused[0], np.ones(len(fused[0]), np.int64), grid) > 0
        skio.write_voxel_bits(seq_dir / "voxels" / f"{t:06d}.bin", occupied)
        current = traversed([np.zeros(3, np.float32)], fused[:1], grid)
        skio.write_voxel_bits(seq_dir / "voxels" / f"{t:06d}.occluded", ~current & ~occupied)
        if scribble_dir is not None:  # the same lines in every frame (a stream of their own: scans unchanged)
            world = np.concatenate([scans[j].xyz for j in range(t, last + 1)])
            keep = scribble_mask(world, p, np.random.default_rng([seed, 0x5C]))
            scribbled = voxelize_majority(np.concatenate(fused)[keep], raw[keep], grid)
            write_scribbles(scribble_dir / "voxels" / f"{t:06d}.label",
                            np.where(voxel_raw != 0, scribbled, 0).astype(np.uint16))
        written += 1
        if progress:
            progress()
    (seq_dir / "poses.txt").write_text("".join(_row(m) + "\n" for m in poses))
    write_calib(seq_dir / "calib.txt", tr, intrinsics(p.camera) if p.camera is not None else None)
    return written


SCRIBBLE_FOLDER = "scribblesc"  # the export's ScribbleSC folder, under its root


def export_kitti(out: str | Path, p: SyntheticParams, sequences: Sequence[str] = ("00", "08"), frames: int = 16,
                 stride: int = 5, progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``sequences`` (names, e.g. the official train "00" and validation "08") as SemanticKITTI sequences under
    ``out/sequences``; sequence NN is the street of seed ``p.seed * 1000 + int(NN)``."""
    if frames < 1 or stride < 1:
        raise DistilkitError(f"export-kitti: frames and stride must be at least 1, got {frames} and {stride}")
    root = Path(out).expanduser()
    total = len(sequences) * len(range(0, frames, stride))
    done = [0]

    def tick() -> None:
        done[0] += 1
        if progress:
            progress(done[0], total)

    for name in sequences:
        if not name.isdigit():
            raise DistilkitError(f"export-kitti: sequence names are numbers such as 00 or 08, got {name!r}")
        export_sequence(root / "sequences" / name, p.seed * 1000 + int(name), p, frames, stride, tick,
                        root / SCRIBBLE_FOLDER / "sequences" / name)
    return root


def synthetic_params(items: Sequence[str], camera: bool = False) -> SyntheticParams:
    """The synthetic streets' parameters from ``KEY=VALUE`` items (values read as YAML), with the camera's defaults
    where ``camera`` asks for images and the items set none."""
    import yaml
    from pydantic import ValidationError

    from distilkit.errors import DistilkitError

    values = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise DistilkitError(f"--set {item!r}: expected KEY=VALUE")
        values[key] = yaml.safe_load(value)
    if camera and values.get("camera") is None:
        values["camera"] = {}
    try:
        return SyntheticParams(**values)
    except ValidationError as err:
        raise DistilkitError(f"--set: {err.errors()[0]['loc'][0]}: {err.errors()[0]['msg']}") from None


__all__ = ["SCRIBBLE_FOLDER", "export_kitti", "export_sequence", "lidar_to_camera", "synthetic_params", "write_calib"]
