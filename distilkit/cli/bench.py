"""``distilkit bench [NAME ...]``: the benchmarks of :mod:`distilkit.bench` — objectives against their papers' naive
forms, samplers, networks, the sparse layer, the data path — each timing a fast form against a naive one side by
side in one run."""

from __future__ import annotations

import argparse
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "bench": ["distilkit bench dskd pkt", "distilkit bench --quick", "distilkit bench determinism loader",
              "distilkit bench step --device cuda --only 'SCPNet student' 'recipe scpnet'"],
}

# every `distilkit bench` NAME with what it times, in the order a run without names takes them (the help lists them
# without importing torch; a test keeps this in step with distilkit.bench.BENCHES)
BENCH_NAMES: dict[str, str] = {
    "dskd": "DSKD's exact O(N C^2) identity against the N x N matrices",
    "pkt": "PKT, blocked, against the dense kernel",
    "rgo2d": "RGO²D, by index_add, against the authors' broadcast masks",
    "kd": "KD over a masked voxel volume",
    "nst": "NST's MMD, by its Gram identity",
    "structural": "ScoreLiDAR's structural loss: key points and the point-wise distance matrices",
    "relation": "L2COcc's relational term in tiles of one GEMM against the dense P x P cosine matrices",
    "bev": "LiCROcc's, MonoOcc's and the voxel-to-BEV terms at their papers' sizes against their releases' forms",
    "sampler": "LiDiff's sampler at 8 against 50 steps",
    "guidance": "LiDiff's sampler with classifier-free guidance against without",
    "complete": "`distilkit complete` on a 125,000-point scan, with and without refinement",
    "determinism": "a training step with the deterministic settings on and off",
    "loader": "an epoch of the quickstart teacher's steps with 2 loader workers and with none",
    "camera": "the camera student's step with and without RGO²D",
    "kitti": "reading, fusing and evaluating SemanticKITTI-sized frames",
    "sparse": "a Cylinder3D-sized submanifold 3x3x3 layer (GFLOP/s vs sgemm) against dense conv3d; table vs loop",
    "sparse-sizes": "the sparse table form against spconv (or the loop) at 20k-400k voxels, 32-128 channels",
    "networks": "each family's network at size tiny and paper: parameters, a training step's time and memory",
    "teacher-store": "a paper teacher's forward against reading its taps from a teacher store, per layout: "
                     "bytes, read time, error",
    "step": "a paper network's or recipe's step in fp32/bf16/fp16: time, memory, syncs, top ops",
}


def add(sub: Any) -> None:
    names = "benchmarks:\n" + "\n".join(f"  {n:<12} {d}" for n, d in BENCH_NAMES.items())
    b = command(sub, "bench", "time objectives forward+backward at realistic sizes", EXAMPLES["bench"], before=names)
    b.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (listed below; default: all)")
    b.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help="where both forms are timed: cpu (default; peak memory is the process's resident size) or cuda "
                        "(the current GPU; peak memory is torch's allocations on it, and the sparse bench also times "
                        "each sparse library present)")
    b.add_argument("--quick", action="store_true", help="small sizes (a smoke test)")
    b.add_argument("--only", nargs="+", metavar="PATTERN",
                   help="run only the cases whose objective or size matches one of these (case-insensitive, anywhere "
                        "in the row's first two cells; `*` for anything between), those of the first pattern first: "
                        "`--only 'recipe*bf16' 'SCPNet student'`")
    b.add_argument("--time-limit", type=float, metavar="SECONDS",
                   help="start no case after this many seconds (a case that times many steps also stops); those left "
                        "are named under the table")
    b.set_defaults(fn=bench)


def bench(args: argparse.Namespace) -> int:
    from distilkit.bench import run_bench

    run_bench(args.names, device=args.device, quick=args.quick, only=args.only, time_limit=args.time_limit)
    return 0
