"""What a user does with trained runs and their predictions: ``distilkit eval`` (SemanticKITTI's official completion
evaluation of a predictions folder), ``distilkit predict`` (a run's predictions in the submission format),
``distilkit export`` (a student's weights alone) and ``distilkit complete`` (a scan completed into a dense scene)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from distilkit.cli.base import command

EXAMPLES = {
    "eval": ["distilkit eval --dataset-root /data/semantickitti --predictions preds --split valid",
             "distilkit eval --classes sscbench-kitti360 --dataset-root /data/KITTI-360 --predictions preds "
             "--split test"],
    "predict": ["distilkit predict runs/NAME/STAGE-* --dataset-root /data/semantickitti --split valid --out preds",
                "distilkit predict runs/NAME/STAGE-* --dataset-root /data/semantickitti --split test --out submission",
                "distilkit predict runs/NAME/STAGE-* --dataset-root /data/KITTI-360 --split test --out preds"],
    "export": ["distilkit export runs/quickstart/student_dskd-* --out student.pt",
               "distilkit export runs/quickstart/student_dskd-* --out student.pt --which last"],
    "complete": ["distilkit complete runs/scorelidar/student-* scan.bin --out scene.ply --steps 8",
                 "distilkit complete runs/scorelidar/student-* scan.bin --out scene.ply --refine "
                 "runs/scorelidar/refined_8-*"],
}


def add(sub: Any) -> None:
    ev = command(sub, "eval", "SemanticKITTI's official completion evaluation of a predictions "
                              "folder (and VoxFormer's 12.8 / 25.6 m range split)",
                              EXAMPLES["eval"])
    _folder_split(ev, "the SemanticKITTI folder (holds sequences/NN/voxels/; sscbench-kitti360: the KITTI-360 "
                      "folder)", "valid", "08")
    ev.add_argument("--predictions", required=True, help="the folder holding `sequences/NN/predictions/*.label` "
                                                         "(sscbench-kitti360: `<drive>/FFFFFF_1_1.npy`)")
    ev.add_argument("--out", default=None, help="where to write the scores (default: PREDICTIONS/scores.txt)")
    ev.add_argument("--classes", default="semantickitti",
                    choices=["semantickitti", "semanticposs", "sscbench-kitti360"],
                    help="the labels' class table and official splits (semanticposs: 11 classes, valid = test = 02; "
                         "sscbench-kitti360: its folder layout, 19 classes, valid 06, test 09, predictions "
                         "PREDICTIONS/<drive>/FFFFFF_1_1.npy or .label)")
    ev.add_argument("--targets", default=None, choices=["voxels", "preprocess"],
                    help="sscbench-kitti360's target files: `voxels/*.label` + `.invalid` (default) or "
                         "`preprocess/labels/*_1_1.npy`")
    ev.set_defaults(fn=evaluate)
    pr = command(sub, "predict", "write a trained SSC run's predictions of a folder in its benchmark's "
                                 "format (SemanticKITTI: sequences/NN/predictions/NNNNNN.label; "
                                 "SSCBench-KITTI-360: <drive>/FFFFFF_1_1.npy)",
                                 EXAMPLES["predict"])
    pr.add_argument("run", help="a stage's run folder or checkpoint (trained on a SemanticKITTI-format or "
                                "SSCBench-KITTI-360 folder)")
    _folder_split(pr, "the folder to predict (the run's dataset's layout)", "test",
                  "11-21; SSCBench-KITTI-360: drive 09")
    pr.add_argument("--out", required=True, help="the folder to write the predictions into")
    pr.add_argument("--device", default="cpu", help="cpu or cuda")
    pr.add_argument("--vote", default=None, metavar="GROUP",
                    help="test-time voting (JS3C-Net's): class probabilities averaged over each frame seen under "
                         "every flip and quarter turn of GROUP, each mapped back — 'train' (the run's "
                         "train.augment) or as in a recipe: '{flip: [x, y], rotate90: z}'")
    pr.set_defaults(fn=predict)
    xp = command(sub, "export", "write a trained student's weights alone (a plain state dict for "
                                "torch.load(weights_only=True) or `init: {checkpoint: ...}`) and a "
                                "JSON of its adapter, parameters and classes",
                                EXAMPLES["export"])
    xp.add_argument("run", help="a stage's run folder (runs/<recipe>/<stage>-<hash>) or a checkpoint file")
    xp.add_argument("--out", "-o", required=True, help="the weights file to write (e.g. student.pt); the JSON goes "
                                                      "beside it (student.json)")
    xp.add_argument("--which", default="best", choices=["best", "last"],
                    help="the run folder's checkpoint: the best validation score (default) or the last step")
    xp.set_defaults(fn=export)
    c = command(sub, "complete", "complete a scan (.bin, .ply, .npy) into a dense scene with a "
                                 "trained point-diffusion model",
                                 EXAMPLES["complete"])
    c.add_argument("checkpoint", help="a checkpoint (best.pt / last.pt) or a stage's run folder")
    c.add_argument("scan", help="the scan: SemanticKITTI .bin, .ply or .npy")
    c.add_argument("--out", "-o", required=True, help="where to write the scene (.ply, .npy or .bin)")
    c.add_argument("--steps", type=int, default=None, help="sampler steps (default: the model's sample_steps)")
    c.add_argument("--guidance", type=float, default=None, help="classifier-free guidance weight (default: the model's)")
    c.add_argument("--scan-points", type=int, default=None,
                   help="points the scan is sampled to (default: what the model was trained with)")
    c.add_argument("--seed", type=int, default=0, help="seed of the sampler's noise")
    c.add_argument("--refine", default=None, metavar="RUN",
                   help="refine the completion with this refinement run (a lidiff-refine stage's folder or checkpoint)")
    c.add_argument("--device", default="cpu", help="cpu or cuda")
    c.set_defaults(fn=complete)


def _folder_split(parser: argparse.ArgumentParser, root_help: str, split: str, split_sequences: str) -> None:
    """``--dataset-root``, and ``--split`` (an official split) or ``--sequences`` (eval and predict)."""
    parser.add_argument("--dataset-root", required=True, help=root_help)
    parser.add_argument("--split", default=split, choices=["train", "valid", "test"],
                        help=f"the official split's sequences (default {split} = {split_sequences})")
    parser.add_argument("--sequences", nargs="+", default=None, help="these sequences instead of the split's")


def evaluate(args: argparse.Namespace) -> int:
    """Every input checked (:func:`~distilkit.metrics.sscbench.plan_sscbench`,
    :func:`~distilkit.metrics.official.plan_folder`) before the progress bar starts, then scored."""
    from distilkit.console import make_console, progress_bar
    from distilkit.data.info import ClassTable
    from distilkit.data.params import KITTI_SPLITS, POSS_SPLITS
    from distilkit.errors import DataError
    from distilkit.metrics.official import evaluate_folder, plan_folder

    console = make_console()
    if args.classes == "sscbench-kitti360":  # its own layout and target rule (distilkit.metrics.sscbench)
        from distilkit.data.sscbench import SPLITS, drive_name
        from distilkit.metrics.sscbench import plan_sscbench, score_sscbench

        sequences = [drive_name(s) for s in args.sequences] if args.sequences else list(SPLITS[args.split])
        plan = plan_sscbench(args.dataset_root, args.predictions, sequences, args.targets or "voxels")
        for note in plan.data.notes:
            console.print(f"[yellow]eval:[/] {note}", highlight=False, soft_wrap=True)
        with progress_bar(console, "eval") as advance:
            ev = score_sscbench(plan, advance)
        return _report(args, console, ev, "SSCBench-KITTI-360 completion", sequences)
    if args.targets is not None:
        raise DataError(f"--targets {args.targets}: only with --classes sscbench-kitti360 (a SemanticKITTI folder's "
                        "targets are its voxels/*.label)")
    poss = args.classes == "semanticposs"
    sequences = args.sequences or list((POSS_SPLITS if poss else KITTI_SPLITS)[args.split])
    table = ClassTable.semanticposs() if poss else ClassTable.semantickitti()
    jobs = plan_folder(args.dataset_root, args.predictions, sequences)
    with progress_bar(console, "eval") as advance:
        ev = evaluate_folder(args.dataset_root, args.predictions, sequences, advance, table, jobs=jobs)
    return _report(args, console, ev, "SemanticKITTI completion", sequences)


def _report(args: argparse.Namespace, console: Any, ev: Any, title: str, sequences: list[str]) -> int:
    """Print an evaluation's table and per-class IoU and write its scores.txt."""
    import yaml
    from rich.table import Table

    from distilkit.files import atomic_write_text
    from distilkit.metrics.official import scores_yaml

    table = Table(title=f"{title}, sequences {' '.join(sequences)}, {ev.frames} frames (%)")
    for col in ("box", "IoU", "precision", "recall", "mIoU"):
        table.add_column(col, justify="left" if col == "box" else "right")
    for name, s in (("51.2 m (whole grid)", ev.scores), *((f"{r:g} m", v) for r, v in sorted(ev.ranges.items(),
                                                                                             reverse=True))):
        table.add_row(name, *(f"{100 * s[k]:.2f}" for k in ("iou", "precision", "recall", "miou")))
    console.print(table)
    console.print("  ".join(f"{n} {100 * v:.1f}" for n, v in zip(ev.names[1:], ev.scores["class_iou"])))
    out = Path(args.out) if args.out else Path(args.predictions) / "scores.txt"
    atomic_write_text(out, yaml.safe_dump(scores_yaml(ev), sort_keys=False))
    console.print(f"scores: {out}")
    return 0


def predict(args: argparse.Namespace) -> int:
    """The run, its data and the folder checked and the model loaded before the progress bar starts."""
    from distilkit.console import make_console, progress_bar
    from distilkit.engine.infer.predict import prepare_prediction, run_prediction

    console = make_console()
    job = prepare_prediction(args.run, args.dataset_root, args.sequences or args.split, args.out, args.device,
                             vote=args.vote)
    for note in getattr(job.dataset, "notes", []):
        console.print(f"[yellow]predict:[/] {note}", highlight=False, soft_wrap=True)
    with progress_bar(console, "predict") as advance:
        n = run_prediction(job, advance)
    unit = "drives" if job.where.endswith("_1_1.npy") else "sequences"
    console.print(f"{n} frames of {unit} {' '.join(job.sequences)} predicted into {job.where}", highlight=False,
                  soft_wrap=True)
    return 0


def export(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.engine.infer.export import export_student

    done = export_student(args.run, args.out, args.which)
    make_console().print(f"{done.weights}: the {done.adapter} student's {done.tensors} tensors (step {done.step}), a "
                         f"plain state dict; {done.sidecar}: its adapter, parameters, data and classes")
    return 0


def complete(args: argparse.Namespace) -> int:
    from distilkit.console import make_console
    from distilkit.engine.infer.complete import complete

    console = make_console()
    with console.status("loading the model") as spinner:
        done = complete(args.checkpoint, args.scan, args.out, steps=args.steps, guidance=args.guidance,
                        scan_points=args.scan_points, seed=args.seed, device=args.device,
                        status=lambda text: spinner.update(text), refine=args.refine)
    console.print(f"{done.out}: {done.output_points:,} points completed from {done.input_points:,} scan points "
                  f"(sampled to {done.scan_points:,}) in {done.steps} steps{', refined' if done.refined else ''}, "
                  f"{done.seconds:.1f} s")
    return 0
