"""A SemanticKITTI-format folder listed without reading a sample: the frames of a split and what the folder lacks
for them (:class:`SemanticKittiFolder`), the dataset's facts (:func:`kitti_info`), the checks ``validate`` makes of a
folder's files and its fingerprint (the names, sizes and modification times of its files) that stands for the data
in a stage's identity. Torch-free: checking a recipe reads it; :mod:`distilkit.data.kitti_folder` reads the samples."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from distilkit.data.camera import CAMERA_FIELDS, rig
from distilkit.data.info import DataInfo
from distilkit.data.lidar import LIDAR_INPUTS, LIDAR_TARGETS
from distilkit.data.params import SemanticKittiParams
from distilkit.data.proposals import proposal_file, proposal_root
from distilkit.data.scribbles import scribble_file, scribble_root
from distilkit.errors import DataError
from distilkit.structures import VoxelGrid

def kitti_info(params: SemanticKittiParams) -> DataInfo:
    """A folder's facts: its class table and grid, and with ``camera`` the left colour camera (KITTI's nominal
    calibration at the requested image size; every sample carries its sequence's own)."""
    cam = params.camera
    return DataInfo(VoxelGrid.semantickitti(params.scale), params.table(),
                    fields=LIDAR_INPUTS | LIDAR_TARGETS | (CAMERA_FIELDS if cam else frozenset())
                    | ({"occluded"} if params.occluded else frozenset())
                    | ({"scribble"} if params.scribbles else frozenset())
                    | ({"proposal"} if params.proposals else frozenset()),
                    cameras=(dataclasses.replace(rig(cam, 0.0), depth="sparse"),) if cam is not None else (),
                    input_frames=params.input_frames)


def folder_problems(d: Path, frames: list[int], labelled: bool, p: SemanticKittiParams) -> list[str]:
    """What a sequence folder lacks for ``frames``, each as 'what: expected where' (relative to the root)."""
    where = f"sequences/{d.name}"
    if not d.is_dir():
        return [f"{where}: missing (expected {where}/velodyne/*.bin"
                + (f" and {where}/{p.voxels}/*.label)" if labelled else ")")]
    if labelled and not frames:
        return [f"{where}/{p.voxels}: no *.label voxel labels"]
    out = []
    for f in frames:
        if not (d / "velodyne" / f"{f:06d}.bin").is_file():
            out.append(f"{where}/velodyne/{f:06d}.bin: missing (the scan of a labelled frame)")
        if p.rectify and labelled and not (d / "labels" / f"{f:06d}.label").is_file():
            out.append(f"{where}/labels/{f:06d}.label: missing (rectify reads the scan's panoptic labels)")
    if p.occluded and labelled:
        out += [f"{where}/voxels/{f:06d}.occluded: missing (occluded: true reads it)" for f in frames
                if not (d / "voxels" / f"{f:06d}.occluded").is_file()]
    if p.scribbles and labelled:
        folder = scribble_root(p.root, p.scribbles)
        out += [f"{scribble_file(folder, d.name, f)}: missing (scribbles: {p.scribbles} reads it)" for f in frames
                if not scribble_file(folder, d.name, f).is_file()]
    if p.proposals and labelled:
        folder = proposal_root(p.root, p.proposals)
        out += [f"{folder / d.name / 'queries'}/{f:06d}.*: missing (proposals: {p.proposals} reads it)"
                for f in frames if proposal_file(folder, d.name, f) is None]
    if p.camera is not None:
        wanted = sorted({max(f - k, 0) for f in frames for k in (0, *p.camera.previous)})
        out += [f"{where}/image_2/{j:06d}.png: missing (the camera's image)" for j in wanted
                if not (d / "image_2" / f"{j:06d}.png").is_file()]
    needs = {"poses.txt": p.input_frames > 1 or bool(p.camera and p.camera.previous),
             "calib.txt": p.input_frames > 1 or p.camera is not None}
    out += [f"{where}/{name}: missing ({'the camera' if p.input_frames == 1 else f'fusing {p.input_frames} scans'} "
            "needs it)" for name, needed in needs.items() if needed and not (d / name).is_file()]
    return out


def scan_problems(d: Path, frames: list[int], voxel_frames: set[int], split: str, p: SemanticKittiParams) -> list[str]:
    """:func:`folder_problems` of a scan dataset: every frame's scan and (but in a test sequence without labels/)
    point labels; the voxel frames' extra files where the parameters read them."""
    where = f"sequences/{d.name}"
    if not d.is_dir():
        return [f"{where}: missing (expected {where}/velodyne/*.bin and {where}/labels/*.label)"]
    if not frames:
        return [f"{where}/velodyne: no *.bin scans"]
    out = folder_problems(d, frames, False, p)
    if split != "test" or (d / "labels").is_dir():
        out += [f"{where}/labels/{f:06d}.label: missing (the scan's point labels)" for f in frames
                if not (d / "labels" / f"{f:06d}.label").is_file()]
    if p.occluded:
        out += [f"{where}/voxels/{f:06d}.occluded: missing (occluded: true reads it)" for f in sorted(voxel_frames)
                if f in frames and not (d / "voxels" / f"{f:06d}.occluded").is_file()]
    return out


class SemanticKittiFolder:
    """The frames of one role of a SemanticKITTI-format folder (the labelled every-5th frames; with
    ``semantickitti-scan``'s parameters every scan), listed and checked file by file without reading them; a
    :class:`~distilkit.data.kitti_folder.SemanticKittiDataset` reads them."""

    def __init__(self, params: SemanticKittiParams, split: str, what: str | None = None) -> None:
        """The role ``split`` (train, val, test) of the folder; ``what`` names it in errors (default: the role)."""
        self.p = params
        self.table = params.table()
        root = Path(params.root).expanduser()
        seqs = params.sequences(split)
        # (sequence dir, frame, sequence length, has voxel labels: a test sequence without any is the benchmark's
        # hidden split, whose every stride-th scan is predicted and never scored)
        self.items: list[tuple[Path, int, int, bool]] = []
        self.notes: list[str] = []  # what a user should hear about the folder (frames left out), shown once
        problems: list[str] = []
        for seq in seqs:
            d = root / "sequences" / seq
            vox = sorted((d / params.voxels).glob("*.label"))
            scans = sorted((d / "velodyne").glob("*.bin"))
            if params.EVERY_SCAN:  # semantickitti-scan: every stride-th scan, voxel targets where the frame has them
                frames = [int(f.stem) for f in scans if int(f.stem) % params.stride == 0]
                problems += scan_problems(d, frames, {int(f.stem) for f in vox}, split, params)
                self.items += [(d, f, len(scans), (d / params.voxels / f"{f:06d}.label").is_file()) for f in frames]
                continue
            frames = [int(f.stem) for f in vox] if vox else [int(f.stem) for f in scans] if split == "test" else []
            frames = [f for f in frames if f % params.stride == 0]
            problems += folder_problems(d, frames, bool(vox) or split != "test", params)
            self.items += [(d, f, len(scans), bool(vox)) for f in frames]
            if vox:  # every 5th scan up to the last labelled one has voxel labels: a gap is a deleted file
                labelled = {int(f.stem) for f in vox}
                gaps = [int(f.stem) for f in scans if int(f.stem) % 5 == 0 and int(f.stem) % params.stride == 0
                        and int(f.stem) < max(labelled) and int(f.stem) not in labelled]
                if gaps:
                    self.notes.append(f"sequences/{seq}: {len(gaps)} of its every-5th frames have a scan but no "
                                      f"{params.voxels}/*.label and are left out ({', '.join(f'{g:06d}' for g in gaps[:5])}"
                                      f"{', ...' if len(gaps) > 5 else ''})")
        if problems or not self.items:
            shown = problems[:12] + ([f"... and {len(problems) - 12} more"] if len(problems) > 12 else [])
            raise DataError(f"{root}: {what or f'split {split!r}'} (sequences {', '.join(seqs) or 'none'}) is not a complete "
                            "SemanticKITTI folder:\n  " + "\n  ".join(shown or [f"no frames with a stride of "
                                                                                   f"{params.stride}"]))


def kitti_check(params: SemanticKittiParams, split: str) -> str | None:
    """What ``distilkit validate`` says of a folder's split: None where it can be read, else the problem (the
    folder missing, or each file it lacks). Only lists and stats files: cheap."""
    root = Path(params.root).expanduser()
    if not (root / "sequences").is_dir():
        return f"{root}: no sequences/ folder there (a SemanticKITTI folder holds sequences/NN/velodyne, ...)"
    try:
        SemanticKittiFolder(params, split)
    except DataError as exc:
        return str(exc)
    return None


def kitti_fingerprint(params: SemanticKittiParams) -> dict[str, Any]:
    """What identifies a SemanticKITTI folder in a stage's identity: the parameters but the root, and a digest of
    the names, sizes and modification times of the files of the sequences it reads (a moved folder keeps its
    stages; a changed file retrains them)."""
    import hashlib

    root = Path(params.root).expanduser()
    lines = []
    for seq in sorted({s for role in ("train", "val", "test") for s in params.sequences(role)}):
        d = root / "sequences" / seq
        folders = dict.fromkeys(("velodyne", "labels", "voxels", params.voxels,
                                 *(("image_2",) if params.camera is not None else ())))
        files = [f for sub in folders for f in sorted((d / sub).glob("*"))]
        files += [d / name for name in ("poses.txt", "calib.txt") if (d / name).is_file()]
        for f in files:
            st = f.stat()
            lines.append(f"{f.relative_to(root).as_posix()} {st.st_size} {st.st_mtime_ns}")
        if params.proposals:  # VoxFormer's proposals, wherever they lie
            folder = proposal_root(root, params.proposals)
            for f in sorted((folder / seq / "queries").glob("*")):
                st = f.stat()
                lines.append(f"proposals/{f.relative_to(folder).as_posix()} {st.st_size} {st.st_mtime_ns}")
        if params.scribbles:  # ScribbleSC's folder, wherever it lies
            folder = scribble_root(root, params.scribbles)
            for f in sorted((folder / "sequences" / seq / "voxels").glob("*.label")):
                st = f.stat()
                lines.append(f"scribbles/{f.relative_to(folder).as_posix()} {st.st_size} {st.st_mtime_ns}")
    return {"params": params.model_dump(mode="json", exclude={"root"}, exclude_defaults=True),
            "files": len(lines), "digest": hashlib.sha256("\n".join(lines).encode()).hexdigest()}


__all__ = ["SemanticKittiFolder", "folder_problems", "kitti_check", "kitti_fingerprint", "kitti_info", "scan_problems"]
