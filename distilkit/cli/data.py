"""``distilkit data rectify`` and ``distilkit data export-kitti``: work on data folders — SCPNet's label rectification
of a SemanticKITTI folder, synthetic streets written as one."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "data": ["distilkit data export-kitti /tmp/kitti --camera", "distilkit data rectify /data/semantickitti"],
    "data rectify": ["distilkit data rectify /data/semantickitti",
                     "distilkit data rectify /data/semanticposs --labels semanticposs"],
    "data export-kitti": ["distilkit data export-kitti /tmp/kitti",
                          "distilkit data export-kitti /tmp/kitti --camera --set beams=64 azimuth_steps=2048"],
}


def add(sub: Any) -> None:
    dp = command(sub, "data", "work on data folders: rectify a SemanticKITTI folder's completion "
                              "labels, export synthetic streets as one",
                              EXAMPLES["data"])
    dsub = dp.add_subparsers(dest="data_command", required=True, metavar="ACTION",
                             help="rectify (SCPNet's label rectification) or export-kitti (synthetic streets as a folder)")
    rect = command(dsub, "rectify", "SCPNet's label rectification: write "
                                    "sequences/NN/voxels_rectified/ beside the original voxel labels "
                                    "(which stay untouched)",
                                    EXAMPLES["data rectify"])
    rect.add_argument("root", help="a SemanticKITTI folder (holds sequences/)")
    rect.add_argument("--sequences", nargs="+", default=None, help="the sequences (default: every one)")
    rect.add_argument("--classes", nargs="+", default=None,
                      help="dynamic classes (default SemanticKITTI: car truck other-vehicle person bicyclist "
                           "motorcyclist)")
    rect.add_argument("--out", default="voxels_rectified", help="the folder written in each sequence")
    rect.add_argument("--labels", default="semantickitti", choices=["semantickitti", "semanticposs"],
                      help="the folder's class table (semanticposs: people, rider and car by default)")
    rect.set_defaults(fn=rectify)
    ex = command(dsub, "export-kitti", "write synthetic streets as a SemanticKITTI folder (scans, "
                                       "panoptic labels, voxels, invalid and occluded masks, poses, "
                                       "calibration, with --camera images)",
                                       EXAMPLES["data export-kitti"])
    ex.add_argument("out", help="the folder to write (sequences/ goes inside)")
    ex.add_argument("--sequences", nargs="+", default=["00", "08"], help="sequence names (default: 00 08)")
    ex.add_argument("--frames", type=int, default=16, help="scans per sequence (default 16)")
    ex.add_argument("--stride", type=int, default=5, help="voxel labels every n-th scan (SemanticKITTI: 5)")
    ex.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="synthetic-lidar parameters, e.g. beams=64 azimuth_steps=2048 gt_frames=10 seed=1 "
                         "'camera={height: 96, width: 320}'")
    ex.add_argument("--camera", action="store_true",
                    help="also render image_2/ (the synthetic camera's defaults unless --set camera=... says more)")
    ex.set_defaults(fn=export_kitti)


def rectify(args: argparse.Namespace) -> int:
    from distilkit.console import make_console, progress_bar
    from distilkit.data.info import ClassTable
    from distilkit.data.rectify import rectify_folder

    console = make_console()
    table = ClassTable.semanticposs() if args.labels == "semanticposs" else ClassTable.semantickitti()
    with progress_bar(console, "rectifying") as advance:
        counts = rectify_folder(args.root, args.sequences, args.classes, args.out, advance, table)
    for name, (before, left) in counts.items():
        share = f"{100 * left / before:.1f} % left" if before else "none"
        console.print(f"{name}: {left:,} of {before:,} voxels left ({share})")
    console.print(f"written to sequences/*/{args.out}/ under {args.root}")
    return 0


def export_kitti(args: argparse.Namespace) -> int:
    from distilkit.console import make_console, progress_bar
    from distilkit.data.export import export_kitti as export, synthetic_params

    params = synthetic_params(args.set, camera=args.camera)
    console = make_console()
    with progress_bar(console, "export-kitti") as advance:
        root = export(args.out, params, args.sequences, args.frames, args.stride, advance)
    console.print(f"{root}: sequences {' '.join(args.sequences)}, {args.frames} scans each, voxel labels every "
                  f"{args.stride}th")
    return 0
