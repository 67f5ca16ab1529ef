"""An SSCBench-KITTI-360 folder listed without reading a sample (the benchmark's layout, formats, classes and the
recipe's parameters are :mod:`distilkit.data.sscbench`'s): a drive's frames listed, each frame's files checked by their
sizes (:class:`SscbenchFrames`), the checks ``validate`` makes of a folder (one frame's labels a drive), the notes it
shows beside them and the folder's fingerprint (the names, sizes and modification times of its files). Torch-free:
checking a recipe reads it; :mod:`distilkit.data.sscbench_folder` reads the frames.

A drive's frames are listed from ``voxels/*.bin``, as the benchmark's loader lists them (``method/MonoScene/monoscene/
data/kitti_360/kitti_360_dataset.py``, ai4ce/SSCBench at 8a27949: ``glob(.../voxels/*.bin)``); a frame with a target
but no ``.bin`` is left out and counted in a note (the release's drive 0003 has four, ``preprocess/labels/``'s
000970-000985: "these extra data will not be loaded by the MonoScene dataloader", ai4ce/SSCBench issue #23).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import numpy as np

from distilkit.data import semantickitti as skio
from distilkit.data.sscbench import LEARNING_MAP, NAMES, SHAPE, VOXELS, SscbenchParams, read_train_ids
from distilkit.errors import DataError

Reads = Literal["all", "targets", "inputs"]  # what a dataset reads: both (training), the targets (eval), the inputs


def _size_problem(path: Path, sizes: tuple[int, ...], what: str) -> str | None:
    if not path.is_file():
        return f"{path.name}: missing ({what})"
    if path.stat().st_size not in sizes:
        return (f"{path.name}: {path.stat().st_size:,} bytes, expected "
                f"{' or '.join(f'{s:,}' for s in sizes)} ({what} of a 256 x 256 x 32 grid)")
    return None


def frame_problems(root: Path, drive: str, frame: str, p: SscbenchParams, reads: Reads = "all") -> list[str]:
    """What one frame lacks (of what ``reads`` asks for) or has at the wrong size, each as 'where: what' relative to
    ``root`` (stat only)."""
    vox = Path("data_2d_raw") / drive / "voxels"
    checks = [(f"{frame}.bin", (VOXELS // 8, VOXELS), "the voxelised input scan")] if reads != "targets" else []
    if p.targets == "voxels" and reads != "inputs":
        checks += [(f"{frame}.label", (2 * VOXELS,), "uint16 voxel labels"),
                   (f"{frame}.invalid", (VOXELS, VOXELS // 8), "the invalid mask")]
    out = [f"{vox}/{msg}" for name, sizes, what in checks if (msg := _size_problem(root / vox / name, sizes, what))]
    if p.targets == "preprocess" and reads != "inputs":
        npy = root / "preprocess" / "labels" / drive / f"{frame}_1_1.npy"
        try:
            shape = np.load(npy, mmap_mode="r", allow_pickle=False).shape if npy.is_file() else None
        except (ValueError, OSError):
            shape = "unreadable"
        if shape != SHAPE:
            out.append(f"{npy.relative_to(root)}: " + ("missing (the preprocessed target)" if shape is None else
                                                       f"shape {shape}, expected {SHAPE}"))
    if p.camera is not None and reads != "targets":
        image = Path("data_2d_raw") / drive / "image_00" / "data_rect" / f"{frame}.png"
        if not (root / image).is_file():
            out.append(f"{image}: missing (the camera's image)")
    return out


def _targets_of(root: Path, drive: str, targets: str) -> tuple[list[str], str]:
    """(the frames of ``drive`` that have a target file, where they are listed from)."""
    if targets == "preprocess":
        folder, suffix = root / "preprocess" / "labels" / drive, "_1_1.npy"
    else:
        folder, suffix = root / "data_2d_raw" / drive / "voxels", ".label"
    frames = sorted(f.name[:-len(suffix)] for f in folder.glob(f"*{suffix}"))
    return frames, f"{folder.relative_to(root).as_posix()}/*{suffix}"


def drive_frames(root: Path, drive: str, targets: str, reads: Reads = "all") -> tuple[list[str], list[str], str]:
    """(a drive's frames, those left out: a target but no input scan, where the frames are listed from). The frames
    are ``voxels/*.bin``'s, as SSCBench's loader lists them (module docstring); scoring a drive whose folder holds
    the targets alone (no ``.bin`` at all) takes every frame with a target."""
    scans = sorted(f.stem for f in (root / "data_2d_raw" / drive / "voxels").glob("*.bin"))
    where = f"data_2d_raw/{drive}/voxels/*.bin"
    if reads == "inputs":
        return scans, [], where
    labelled, target_where = _targets_of(root, drive, targets)
    if reads == "targets" and not scans:
        return labelled, [], target_where
    have = set(scans)
    return scans, [f for f in labelled if f not in have], where


def _listed(frames: list[str], most: int = 5) -> str:
    return ", ".join(frames) if len(frames) <= most else f"{', '.join(frames[:most - 1])}, ..., {frames[-1]}"


class SscbenchFrames:
    """An SSCBench-KITTI-360 folder's frames of one role, listed and checked by their files' sizes without reading
    them: every ``voxels/*.bin`` of its drives (module docstring). ``reads``: what is checked — ``all`` (training),
    ``targets`` (scoring: no input scan) or ``inputs`` (predicting: no target); a
    :class:`~distilkit.data.sscbench_folder.SscbenchDataset` reads the frames."""

    def __init__(self, params: SscbenchParams, split: str, what: str | None = None, reads: Reads = "all") -> None:
        self.p = params
        self.reads = reads
        self.root = root = Path(params.root).expanduser()
        drives = params.sequences(split)
        self.items: list[tuple[str, str]] = []
        self.notes: list[str] = []  # what a user should hear about the folder (frames left out), shown once
        problems: list[str] = []
        for drive in drives:
            frames, label_only, where = drive_frames(root, drive, params.targets, reads)
            if label_only:
                self.notes.append(_left_out(drive, label_only))
            if not frames:
                problems.append(_no_frames(root, drive, where, label_only))
                continue
            for f in frames:
                problems += frame_problems(root, drive, f, params, reads)
            self.items += [(drive, f) for f in frames]
        if problems or not self.items:
            shown = problems[:12] + ([f"... and {len(problems) - 12} more"] if len(problems) > 12 else [])
            raise DataError(f"{root}: {what or f'split {split!r}'} (drives {', '.join(drives) or 'none'}) is not a "
                            "complete SSCBench-KITTI-360 folder:\n  " + "\n  ".join(shown or ["no frames"]))

    def __len__(self) -> int:
        return len(self.items)

    def sample_id(self, i: int) -> str:
        """``<drive>/<frame>``, as the benchmark names its files."""
        return "/".join(self.items[i])


def _no_frames(root: Path, drive: str, where: str, label_only: list[str]) -> str:
    """The line for a drive with no frame: its folder missing, or none of the files its frames are listed from."""
    parent = where.rsplit("/", 1)[0]
    if not (root / parent).is_dir():
        drive_missing = parent.startswith("data_2d_raw") and not (root / "data_2d_raw" / drive).is_dir()
        return f"{f'data_2d_raw/{drive}' if drive_missing else parent}: missing (expected {where})"
    n = len(label_only)
    return f"{where}: none there" + (f" ({n} frame{'s have' if n > 1 else ' has'} a target but no .bin input)"
                                     if n else "")


def unmapped_problem(path: str | Path) -> str | None:
    """Where most labelled voxels of a ``.label`` file hold raw ids that kitti360.yaml's learning map lacks (training
    would ignore them all: a drive labelled with KITTI-360's own ids), the line saying so; else None."""
    raw = skio.read_voxel_labels(path, SHAPE)
    labelled = raw[raw > 0]
    unknown = labelled[~np.isin(labelled, np.array(list(LEARNING_MAP)))]
    if not labelled.size or unknown.size * 2 <= labelled.size:
        return None
    ids, counts = np.unique(unknown, return_counts=True)
    common = ", ".join(str(int(i)) for i in ids[np.argsort(-counts, kind="stable")][:5])
    return (f"{path}: {unknown.size / labelled.size:.0%} of its labelled voxels hold raw ids that kitti360.yaml's "
            f"learning map lacks ({common}{', ...' if ids.size > 5 else ''}), which training would ignore: SSCBench's "
            "labels are in SemanticKITTI's raw ids (car 10, road 40, building 50); labels in KITTI-360's own ids "
            "(car 26, road 7, building 11) must be mapped to them first")


def first_frame_problems(data: SscbenchFrames) -> list[str]:
    """The first frame of each drive read: its target's ids (most outside the learning map is a problem), or its
    ``*_1_1.npy`` as train ids."""
    out, seen = [], set()
    for drive, frame in data.items:
        if drive in seen:
            continue
        seen.add(drive)
        try:
            if data.p.targets == "preprocess":
                read_train_ids(data.root / "preprocess" / "labels" / drive / f"{frame}_1_1.npy", len(NAMES))
            elif problem := unmapped_problem(data.root / "data_2d_raw" / drive / "voxels" / f"{frame}.label"):
                out.append(problem)
        except DataError as exc:
            out.append(str(exc))
    return out


def sscbench_check(params: SscbenchParams, split: str) -> str | None:
    """What ``distilkit validate`` says of a role's drives: None where they can be read, else every problem (file
    names and sizes, and one frame's labels a drive: cheap)."""
    root = Path(params.root).expanduser()
    if not (root / "data_2d_raw").is_dir():
        return (f"{root}: no data_2d_raw/ folder there (an SSCBench-KITTI-360 folder holds data_2d_raw/"
                "2013_05_28_drive_NNNN_sync/voxels/, ...)")
    try:
        problems = first_frame_problems(SscbenchFrames(params, split))
        if params.camera is not None:  # the calibration files, where the folder has them, must parse
            from distilkit.data.sscbench_camera import calibration

            calibration(root, params.camera.rectify_rotation)
    except DataError as exc:
        return str(exc)
    return "\n  ".join(problems) or None


def _left_out(drive: str, label_only: list[str]) -> str:
    n = len(label_only)
    return (f"data_2d_raw/{drive}: {n} frame{'s' * (n > 1)} with a target but no voxels/*.bin input left out, as "
            f"SSCBench's loader lists frames from voxels/*.bin ({_listed(label_only)})")


def sscbench_notes(params: SscbenchParams, split: str) -> list[str]:
    """What ``distilkit validate`` tells of a role's drives beside its problems: the frames left out (a target but
    no input scan), per drive (file names only)."""
    root = Path(params.root).expanduser()
    out = []
    for drive in params.sequences(split):
        _, label_only, _ = drive_frames(root, drive, params.targets)
        if label_only:
            out.append(_left_out(drive, label_only))
    return out


def sscbench_fingerprint(params: SscbenchParams) -> dict[str, Any]:
    """The parameters but the root, and a digest of the names, sizes and modification times of the files read."""
    import hashlib

    root = Path(params.root).expanduser()
    lines = []
    for drive in sorted({s for role in ("train", "val", "test") for s in params.sequences(role)}):
        folders = [root / "data_2d_raw" / drive / "voxels", root / "preprocess" / "labels" / drive]
        if params.camera is not None:
            folders += [root / "data_2d_raw" / drive / "image_00" / "data_rect", root / "calibration"]
        for f in (f for folder in folders for f in sorted(folder.glob("*"))):
            st = f.stat()
            lines.append(f"{f.relative_to(root).as_posix()} {st.st_size} {st.st_mtime_ns}")
    return {"params": params.model_dump(mode="json", exclude={"root"}, exclude_defaults=True),
            "files": len(lines), "digest": hashlib.sha256("\n".join(lines).encode()).hexdigest()}


__all__ = ["Reads", "SscbenchFrames", "drive_frames", "first_frame_problems", "frame_problems", "sscbench_check",
           "sscbench_fingerprint", "sscbench_notes", "unmapped_problem"]
